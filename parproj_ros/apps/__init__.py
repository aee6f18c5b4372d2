"""The applications: the ``parproj`` command, ``process``, ``import``, the demo."""
