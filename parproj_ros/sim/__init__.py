"""The simulator: terrain, pushbroom rendering, scenarios, and their recording into bags."""
