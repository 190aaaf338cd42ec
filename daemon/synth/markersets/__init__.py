"""Marker sets for the synthetic performer (TOML package data)."""
