"""HDP learning infrastructure: --config, checkpoints, training curves, torchrun; torch only inside functions."""
