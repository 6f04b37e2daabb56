"""The live reduced simulation (SPEC §9): the learned models drive the grains; measured against NDEM."""
