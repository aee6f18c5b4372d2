"""Image side of the simulator: terrain (height field + texture) and pushbroom scene rendering."""
