"""Where every artifact lives: deterministic layout, atomic writes, checkpoints, manifests."""
