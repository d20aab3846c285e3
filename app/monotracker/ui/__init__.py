"""The web app (viser) over the engine Session: see ``monotracker.ui.app``."""
