"""`fieldcal demo`: run the whole pipeline on a built-in simulated lens (no hardware). Not implemented yet (issue 2)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "demo", "run the whole pipeline on a built-in simulated lens (no hardware) [not implemented yet]", "fieldcal demo --out demo-out")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal demo` is not implemented yet (tracked in issue 2)",
                            fix="use the stages that exist; see README.md")
