"""`mehs export` — placeholder until its issue lands (replace this module)."""

from mehs.errors import MehsError


def configure(parser):
    pass


def run(args):
    raise MehsError("'mehs export' is not implemented yet")
