"""Pure math with no other monose3 imports (but errors): rotations, poses, the pinhole camera
and robust pose averaging. numpy or torch alike where the math is element-wise."""
