"""Ready-made workspaces: the seed paper's default workspace and generators
(``workspaces``), and the benchmark scenarios with goals and starts (``scenarios``)."""
