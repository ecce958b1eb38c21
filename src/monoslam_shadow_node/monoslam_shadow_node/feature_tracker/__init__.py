"""The feature_tracker node: corners tracked across images, re-found by their predictions."""
