"""Body maths: the SMPL-X skeleton and forward kinematics, rotations, the regions' feature layouts, root motion."""
