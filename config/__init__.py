"""Shipped configuration files (YAML, robot descriptions, Zenoh configs); read via shared.config."""
