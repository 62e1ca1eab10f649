"""Zenoh service processes (thin shells around the core); installed as ``confnav.services``."""
