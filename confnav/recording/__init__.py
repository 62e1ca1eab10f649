"""MCAP recordings without Zenoh: layout (channels, schemas, metadata), reading and
inspecting (``inspect``), recovering an unfinished file (``recover``), re-checking recorded
commands against the controller code (``replay_check``) and Foxglove scene channels (``scene``).
"""
