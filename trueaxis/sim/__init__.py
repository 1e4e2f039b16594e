"""trueaxis.sim (layer 5, docs/architecture.md): the virtual shop: effects, cutting, the envelope, the virtual CMM."""
