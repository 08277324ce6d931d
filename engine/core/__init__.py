"""Errors, shape checks and validators, frames and cameras, colour encodings, the config bridge."""
