"""Helpers shared by several test modules (tests/ is on sys.path: setup.cfg's pythonpath).

``scenes``, ``diagnostics`` and ``rasters`` import no ROS (the ROS-free run may use them);
``live`` is for tests marked ros.
"""
