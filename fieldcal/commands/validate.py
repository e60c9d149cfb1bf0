"""`fieldcal validate`: end-to-end check against a simulated lens's truth. Not implemented yet (issue 7)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "validate", "end-to-end check against a simulated lens's truth [not implemented yet]", "fieldcal validate models/triplet-uncorrected.json --out validation")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal validate` is not implemented yet (tracked in issue 7)",
                            fix="use the stages that exist; see README.md")
