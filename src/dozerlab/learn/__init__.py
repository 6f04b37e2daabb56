"""Force/torque models learned from field stores: datasets, models, training, validation and
the MLflow pyfunc model (docs/models.md)."""
