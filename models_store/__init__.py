"""Model registry: SQL metadata and checksummed blobs (lands with the service issue)."""
