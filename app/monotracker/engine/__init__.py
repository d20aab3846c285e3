"""The engine: one surgical session owning plan, threads, events and persistence.

``from monotracker.engine import Session, SessionConfig`` -- see ``session.py`` for the API.
"""

from monotracker.engine.config import SessionConfig
from monotracker.engine.events import Event
from monotracker.engine.session import Session
from monotracker.engine.snapshot import CommandResult, Snapshot

__all__ = ["Session", "SessionConfig", "Event", "CommandResult", "Snapshot"]
