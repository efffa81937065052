"""Built-in mergers: virtual exposures from groups of binary frames."""
