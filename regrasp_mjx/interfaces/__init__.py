"""Layer 6, the field's interfaces: Playground-style registry.load, the gymnasium environments and our
demonstrations as a Minari dataset."""
