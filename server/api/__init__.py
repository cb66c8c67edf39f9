"""The REST control plane: configuration, bone sources, the session manager, the FastAPI app
and its routes, Prometheus metrics, and ``ServerStack`` (everything ``burrforce serve`` runs)."""
