"""`fieldcal plan`: make a focal-stack or focal-sweep plan from a lens profile. Not implemented yet (issue 4)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "plan", "make a focal-stack or focal-sweep plan from a lens profile [not implemented yet]", "fieldcal plan stack lens.json --fs 80 --q 0.05 --out plan.json")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal plan` is not implemented yet (tracked in issue 4)",
                            fix="use the stages that exist; see README.md")
