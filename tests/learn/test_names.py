"""One list of force-model names: the schema, the backbones and the CLI offer exactly it."""

from dozerlab.cli import build_parser
from dozerlab.config import load_config, schema
from dozerlab.learn.models import BACKBONES
from dozerlab.learn.names import MODEL_NAMES


def test_schema_enum_and_default_are_the_model_names():
    models = schema()["properties"]["learn"]["properties"]["models"]
    assert tuple(models["items"]["enum"]) == MODEL_NAMES
    assert tuple(load_config()["learn"]["models"]) == MODEL_NAMES


def test_every_name_has_a_backbone_and_every_backbone_a_name():
    assert tuple(BACKBONES) == MODEL_NAMES


def test_train_command_offers_the_model_names():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    model = next(a for a in sub.choices["train"]._actions if a.dest == "model")
    assert tuple(model.choices) == MODEL_NAMES
