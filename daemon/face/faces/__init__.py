"""Shipped face configs (TOML package data); format: ``face_config``."""
