"""Everything that crosses an HDP node boundary: messages, conversions, topics, runtime."""
