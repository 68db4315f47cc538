"""safemimic's shared library: messages, codec, bus, config, geometry, skeleton.

Every service imports from here; nothing here imports a service.
"""
