"""Navigation on a solved map: navigation functions (``navfn``: Koditschek-Rimon;
``harmonic``: Green's function), critical points and automatic k (``critical``), either one
by name (``factory.make_navfn``), the feedback law (``control``), differential drive
(``unicycle``), kinematic simulation (``sim``), shortest paths and baselines for benchmarks,
and ``messages``: building controllers from wire messages. No Zenoh, no I/O.
"""
