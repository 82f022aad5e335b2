"""The Franka Panda as every HDP package sees it: model constants, kinematics, timing, planning."""
