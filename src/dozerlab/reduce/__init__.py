"""The live reduced simulation (docs/models.md): the learned models drive the grains; measured against NDEM."""
