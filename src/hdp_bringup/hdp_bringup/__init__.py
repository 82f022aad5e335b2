"""Bringing the HDP graph up: launch files, parameters, `hdp launch` and `hdp demo`."""
