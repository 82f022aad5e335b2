"""controller_node's low-level methods by name: the one list that policy.load_policy, controller_node,
`hdp launch`, `hdp demo` and `hdp eval low-level` accept. Imports nothing, so a command line can check a
method without loading torch."""

METHODS = ('rkd', 'rkd_redraw', 'rkd_single', 'planner', 'planner_rrt', 'pose_ik', 'joint', 'joint_guided')
LEARNED = ('rkd', 'rkd_redraw', 'rkd_single', 'pose_ik', 'joint', 'joint_guided')   # they read the checkpoint and the camera's points
# RK-Diffuser three ways, so each part's share of its success is a figure (Table 2):
#   rkd_single  the paper's: one draw of both diffusers, the joint sample refined onto the pose sample;
#   rkd_redraw  + draws again while refinement leaves the end off the NBP, keeping the nearest;
#   rkd         + when every draw stalls, the nearest draw's poses tracked from the arm's configuration.
RKD_VARIANTS = ('rkd_single', 'rkd_redraw', 'rkd')
# The joint diffuser alone, two ways: joint, the raw sample (the paper's Joint Diffusion row);
# joint_guided, each denoising step's estimate pulled onto the NBP through kinematics (no pose diffuser).
