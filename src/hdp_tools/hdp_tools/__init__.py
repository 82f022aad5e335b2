"""The `hdp` command (hdp_tools.cli) and general tools: topic, node, bench transport."""
