"""The odometry_ingest node: wheel odometry to keyframe increments (eq. 2)."""
