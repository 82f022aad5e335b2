"""The `hdp` command line: one entry point, subcommands contributed by every package."""
