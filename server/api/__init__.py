"""The REST control plane: configuration, bone sources, domain errors (``errors``), the
services that own the server's state (sessions, workers, loading, settings, recordings,
storage, housekeeping) behind the ``ControlPlane`` façade (``plane``), the FastAPI app and its
routes, Prometheus metrics, and ``ServerStack`` (everything ``burrforce serve`` runs)."""
