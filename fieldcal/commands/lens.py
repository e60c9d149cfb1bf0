"""`fieldcal lens`: build simulated lenses (e.g. from a prescription). Not implemented yet (issue 7)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "lens", "build simulated lenses (e.g. from a prescription) [not implemented yet]", "fieldcal lens from-prescription table.csv --out lens.json")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal lens` is not implemented yet (tracked in issue 7)",
                            fix="use the stages that exist; see README.md")
