"""Files in and out: MCAP bags, GCP files, DEM tiles, rasters with RPC, safe file handling."""
