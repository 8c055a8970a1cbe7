"""Layer 6, the field's interfaces: Playground-style registry.load and the gymnasium environments."""
