"""Interoperability and evidence (engine level): session recording and replay, the OpenIGTLink
server for 3D Slicer / PLUS. The ct/registration/vision layers never import this package."""
