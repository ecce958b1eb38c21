"""Rigid-body geometry shared by every package: planar poses (``se2``), rotations
(``so3``), unit quaternions (``quaternion``) and 3D frames and transforms (``se3``).

Conventions: angles in rad wrapped to (-pi, pi] by ``se2.wrap_angle``; quaternions
(w, x, y, z) with the Hamilton product; rotation matrices R_a_b map b-coordinates to
a-coordinates; transforms are 4 x 4 homogeneous matrices T_a_b.
"""
