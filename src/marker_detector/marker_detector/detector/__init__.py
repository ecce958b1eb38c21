"""The marker_detector node: fiducial markers in camera images to range-bearing sightings."""
