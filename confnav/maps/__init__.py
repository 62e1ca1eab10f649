"""Workspaces from the real world: robot footprints (``footprint``: the free space
shrunk by a robot's radius) and ROS occupancy-grid maps (``occupancy``)."""
