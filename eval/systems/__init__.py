"""The closed loop's Drake systems: sensor, model and safety filter, each a LeafSystem with named ports."""
