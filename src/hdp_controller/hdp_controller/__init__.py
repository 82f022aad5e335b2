"""HDP low-level policy: RK-Diffuser from next-best pose to Panda joint trajectory."""
