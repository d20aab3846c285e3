"""The headless demo: the whole closed loop on the digital twin, an application beside ``ui/``.

``run.py`` drives a :class:`~monotracker.engine.Session` exactly as the web app does, on a simulated
clock, and measures it against the simulator's truth (:func:`run.run_demo`); ``commands.py`` is
``monotracker demo --headless``. It talks to the engine through the session's public API and its
listener seams only.
"""
