"""Built-in sources: photon cubes, SwissSPAD readouts, high-speed video, simulators."""
