"""HTTP routes, one module per area: health, operations, jobs."""
