"""The bounded JSON reader's old address, kept for the service's imports: the reader is
:mod:`panogs_core.bounded_json`, on the core's bottom floor, because the language package (below ``io``) reads user
vocabularies with it. Import from there; this module goes once nothing imports it."""

from __future__ import annotations

from panogs_core.bounded_json import JsonLimitError, JsonLimits, JsonSyntaxError, loads, read_json_file

__all__ = ["JsonLimitError", "JsonLimits", "JsonSyntaxError", "loads", "read_json_file"]
