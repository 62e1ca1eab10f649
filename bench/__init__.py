"""Benchmarks; ``python -m bench NAME`` regenerates one (see bench/__main__.py)."""
