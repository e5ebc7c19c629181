"""The one base class of zk0's user-facing errors.

Each is raised for bad input (a run-config value, a registry entry, a dataset, an asset
request) with a message of one sentence naming the bad value and what was expected, so
entry points can print it as it is instead of a traceback.
"""

# The Flower error code of a reply a client refused with a Zk0Error: its reason is the sentence.
REFUSED = 100


class Zk0Error(ValueError):
    """Bad input, explained in one sentence."""
