"""The engine: one surgical session owning plan, threads, events and persistence.

``from monotracker.engine import Session, SessionConfig`` -- see ``session.py`` for the API.
"""
from typing import TYPE_CHECKING

from monotracker._lazy import lazy_exports

if TYPE_CHECKING:  # the names below, imported on first use (monotracker/_lazy.py: a fast CLI start)
    from monotracker.engine.config import SessionConfig
    from monotracker.engine.events import Event
    from monotracker.engine.session import Session
    from monotracker.engine.snapshot import CommandResult, Snapshot

__all__ = ["Session", "SessionConfig", "Event", "CommandResult", "Snapshot"]

__getattr__, __dir__ = lazy_exports(__name__, {
    "SessionConfig": "monotracker.engine.config",
    "Event": "monotracker.engine.events",
    "Session": "monotracker.engine.session",
    "CommandResult": "monotracker.engine.snapshot",
    "Snapshot": "monotracker.engine.snapshot",
})
