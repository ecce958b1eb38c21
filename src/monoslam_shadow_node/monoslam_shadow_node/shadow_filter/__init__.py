"""The shadow_filter node: bearing-only tracking and static/dynamic classification per feature."""
