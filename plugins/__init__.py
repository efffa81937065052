"""The built-in plugins of photonpano, registered through the ``photonpano.plugins`` entry points."""
