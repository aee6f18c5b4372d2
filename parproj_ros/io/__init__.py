"""Files in: GCP files, DEM tiles, rasters with RPC; safe reading and writing of files (no ROS)."""
