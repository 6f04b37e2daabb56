"""Field-evolution models: how the velocity and density fields around the blade evolve."""
