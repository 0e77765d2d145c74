"""CLI verbs: one module per family, each exposing ``register(subparsers)``."""
