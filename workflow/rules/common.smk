# Shared helpers of the rules: the validated config and the sweep's target paths.
import json

from dozerlab.config import load_config

# Validate before any job runs: a bad value stops here with its field name and allowed range.
config.update(load_config(config))


def all_targets():
    return []
