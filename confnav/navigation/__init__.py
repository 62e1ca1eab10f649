"""Navigation on a solved map: navigation functions (``navfn``: Koditschek-Rimon;
``harmonic``: Green's function), critical points and automatic k (``critical``), either one
by name (``factory.make_navfn``), the feedback law (``control``), differential drive
(``unicycle``), the safety layer on exact geometry (``safety``), kinematic simulation
(``sim``), shortest paths and baselines for benchmarks, and ``messages``: what a host publishes
from the law's output (building controllers from wire messages is
``confnav.services.navigation``). No Zenoh, no I/O, no threads.
"""
