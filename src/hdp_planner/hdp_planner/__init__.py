"""HDP high-level agent: next-best end-effector pose from language and RGB-D."""
