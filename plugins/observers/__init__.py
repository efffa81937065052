"""Built-in observers: extra outputs written from the run's lifecycle hooks."""
