"""`fieldcal composite`: composite a stack into an all-in-focus image. Not implemented yet (issue 5)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "composite", "composite a stack into an all-in-focus image [not implemented yet]", "fieldcal composite STACK --profile lens.json --out image.tiff")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal composite` is not implemented yet (tracked in issue 5)",
                            fix="use the stages that exist; see README.md")
