"""The HTTP API (FastAPI): /v1 scenes, jobs, metrics and artifacts; /healthz, /readyz, /metrics."""
