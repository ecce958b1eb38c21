"""A feature's status as every node publishes it (slam_interfaces/ShadowTrack.status)."""

PENDING, STATIC, DYNAMIC = 0, 1, 2
STATUS_NAMES = {PENDING: 'PENDING', STATIC: 'STATIC', DYNAMIC: 'DYNAMIC'}
