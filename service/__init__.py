"""sarship service: FastAPI job API (OGC API - Processes shape), durable SQLite job store,
job runner on the Dask cluster (docs/interfaces/rest.md)."""
