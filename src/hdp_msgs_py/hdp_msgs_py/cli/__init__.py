"""Moved: the `hdp` command is hdp_tools.cli; only main's notice stays here, for old command lines."""
