"""Scene assembly, resampling into the normalized geometry, tie-point matching, previews."""
