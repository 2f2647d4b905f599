"""The rule for free text that a client gives and the service stores (a scene's name, an upload's file name, an
Idempotency-Key): printable characters only.

PostgreSQL's text columns refuse U+0000 outright (the driver raises before the row is sent), SQLite stores it, and
control characters in a name garble every listing and log line that shows it. One rule, applied where the text
enters, gives both databases the same answer: a 422 naming the field, before anything is written.
"""

from __future__ import annotations

from service.errors import InvalidInput


def printable_text(value: str, field: str) -> str:
    """``value`` unchanged when every character is printable (spaces included); else InvalidInput naming ``field``.

    >>> printable_text("living room 2", "name")
    'living room 2'
    """
    bad = next((i for i, ch in enumerate(value) if not (ch.isprintable() or ch == " ")), None)
    if bad is not None:
        raise InvalidInput(
            f"{field}: character {bad} is {value[bad]!r} (U+{ord(value[bad]):04X}), a control or separator "
            "character; use printable text"
        )
    return value
