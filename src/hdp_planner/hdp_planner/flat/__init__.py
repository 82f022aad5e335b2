"""The paper's flat baselines (Table 1): Diffusion Policy and ACT, acting in joint space at a flat
policy's rate from both cameras' RGB, proprioception and the instruction; no next-best poses.

dataset (episodes -> (observation, action chunk) samples at the flat rate, cached), networks
(diffusion_policy, act, their shared observation encoder in encoders), train, policy (FlatPolicy:
reset(instruction), act(observation) -> joint-target chunk), checkpoint.
"""

POLICIES = ('diffusion_policy', 'act')
