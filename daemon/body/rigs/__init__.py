"""Shipped rig files (TOML package data); reference: RIGS.md."""
