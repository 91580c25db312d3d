"""Built-in closed-loop policies."""
