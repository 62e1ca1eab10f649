"""confnav: conformal navigation transformation for polygonal workspaces."""
__version__ = "0.1.0"
