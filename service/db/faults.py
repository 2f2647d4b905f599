"""What a database error means for the request that met it: the client's conflict, an outage worth retrying, or a
bug.

SQLAlchemy wraps every driver error in one of a few classes, and the class alone does not tell an outage from a
bug (SQLite raises ``OperationalError`` both for "database is locked" and for "no such table"). The driver's own
code does: PostgreSQL's SQLSTATE (psycopg's ``sqlstate``) and SQLite's extended result code name
(``sqlite_errorname``).
"""

from __future__ import annotations

from enum import Enum

from sqlalchemy.exc import DataError, DBAPIError, IntegrityError, InterfaceError, OperationalError, SQLAlchemyError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError


class DatabaseFault(Enum):
    """The kinds of database error, by who should act on them."""

    DUPLICATE = "duplicate"  # a unique key is taken: the client's conflict
    MISSING_REFERENCE = "missing_reference"  # a row refers to one that does not exist (any more)
    CONSTRAINT = "constraint"  # a NOT NULL or CHECK rule refused a value
    OUTAGE = "outage"  # unreachable, restarting, locked, out of resources: retry shortly
    BUG = "bug"  # anything else (bad SQL, a missing table): the server's fault, logged with its traceback


_DUPLICATE_CODES = {"23505", "SQLITE_CONSTRAINT_UNIQUE", "SQLITE_CONSTRAINT_PRIMARYKEY"}
_MISSING_REFERENCE_CODES = {"23503", "SQLITE_CONSTRAINT_FOREIGNKEY"}
_CONSTRAINT_CODES = {"23502", "23514", "SQLITE_CONSTRAINT_NOTNULL", "SQLITE_CONSTRAINT_CHECK"}
# PostgreSQL SQLSTATE classes that pass: 08 connection exception, 40 transaction rollback (serialization failure,
# deadlock), 53 insufficient resources, 57 operator intervention (shutdown, statement timeout), 55P03 lock
# not available.
_TRANSIENT_SQLSTATE_PREFIXES = ("08", "40", "53", "57", "55P03")
_TRANSIENT_SQLITE_PREFIXES = ("SQLITE_BUSY", "SQLITE_LOCKED", "SQLITE_IOERR", "SQLITE_FULL", "SQLITE_CANTOPEN")


def driver_code(exc: DBAPIError) -> str:
    """The driver's code of the error (SQLSTATE or SQLite's result code name), or "" when it has none."""
    orig = exc.orig
    code = getattr(orig, "sqlstate", None) or getattr(orig, "sqlite_errorname", None)
    return str(code) if code else ""


def classify(exc: SQLAlchemyError) -> DatabaseFault:
    """Which :class:`DatabaseFault` ``exc`` is."""
    if isinstance(exc, PoolTimeoutError):
        return DatabaseFault.OUTAGE  # every pooled connection is busy: capacity, not a bug
    if not isinstance(exc, DBAPIError):
        return DatabaseFault.BUG
    if isinstance(exc, IntegrityError):
        return _integrity_fault(driver_code(exc))
    if isinstance(exc, DataError):
        # A value the database cannot hold (a NUL in a PostgreSQL text column, a number out of range): the value
        # is refused, as by a CHECK rule; the API checks stored text first (service/stored_text.py).
        return DatabaseFault.CONSTRAINT
    if exc.connection_invalidated or isinstance(exc, InterfaceError):
        return DatabaseFault.OUTAGE
    if isinstance(exc, OperationalError) and _is_transient(driver_code(exc)):
        return DatabaseFault.OUTAGE
    return DatabaseFault.BUG


def _integrity_fault(code: str) -> DatabaseFault:
    if code in _MISSING_REFERENCE_CODES:
        return DatabaseFault.MISSING_REFERENCE
    if code in _CONSTRAINT_CODES:
        return DatabaseFault.CONSTRAINT
    # Unique keys, and an integrity error whose driver gives no code: in both, the request clashes with data.
    return DatabaseFault.DUPLICATE


def _is_transient(code: str) -> bool:
    if not code:
        return True  # psycopg gives no SQLSTATE when it never reached the server (refused, timed out)
    if code.startswith("SQLITE_"):
        return code.startswith(_TRANSIENT_SQLITE_PREFIXES)
    return code.startswith(_TRANSIENT_SQLSTATE_PREFIXES)
