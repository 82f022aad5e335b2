"""What crosses an HDP node boundary: message classes and their CDR codec, conversions, topics, outcomes."""
