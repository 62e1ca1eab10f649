"""Wire and MCAP message models (pydantic v2); installed as ``confnav.schemas``."""
