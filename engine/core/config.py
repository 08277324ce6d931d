"""Typed dataclass configs: one helper for fields whose one-line help doubles as command-line help.

``engine.cli.add_dataclass_options`` turns every field of such a config into a ``--option`` with that
help text; the config that produced a run is saved beside its outputs as JSON.
"""
from __future__ import annotations

from dataclasses import field
from typing import Any


def option(default: Any, help_text: str, **kwargs: Any) -> Any:
    """A dataclass field with a default and ``metadata['help']`` (its documentation and CLI help)."""
    return field(default=default, metadata={"help": help_text}, **kwargs)
