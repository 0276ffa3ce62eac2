"""HTTP routes, one module per area: operations, jobs, sessions, health, web."""
