"""Figures (matplotlib): the map and its circle domain (``conformal``), level sets and
trajectories (``navigation``)."""
