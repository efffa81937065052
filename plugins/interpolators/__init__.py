"""Built-in interpolators: homographies for every binary frame from keyframes."""
