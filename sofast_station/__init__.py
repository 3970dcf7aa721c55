"""sofast-station: a production-line fringe-reflection (deflectometry) station for solar mirror facets."""

__version__ = "0.3.1"
