"""What travels and how it is combined: the ClientApp's handlers, the wire format, validation and
aggregation, server optimisers, owner-level DP, robust rules, personal models, the round's observer."""
