"""One error type for bad input, carrying the offending field.

Every layer (library, CLI, service) reports user mistakes through `InputError`, so the
CLI can print it and the service can turn it into a 422 with the field named.
"""


class InputError(ValueError):
    """Bad user input: `field` names what is wrong, `reason` says why."""

    def __init__(self, field: str, reason: str):
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason
