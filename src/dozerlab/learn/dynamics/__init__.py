"""Field-evolution models: how the velocity and density fields in front of the blade evolve."""
