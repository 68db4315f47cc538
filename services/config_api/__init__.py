"""The config API (architecture §1): the single writer of the stack's parameters.

A FastAPI app served by uvicorn: REST to read and change the configuration (validated, persisted
atomically with a version and a history, published as ``ConfigUpdate`` on Zenoh, acknowledged by
the safety service's ``SafetyStatus``), live status over server-sent events and a web console.
"""
