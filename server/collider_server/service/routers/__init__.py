"""HTTP routes, one module per group; each only translates between HTTP and plain functions."""
