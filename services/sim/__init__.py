"""Simulator: the MuJoCo world standing in for the bag, the object, the camera and the two CR5 controllers."""
