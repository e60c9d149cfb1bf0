"""`fieldcal capture`: run a plan on a stage and camera. Not implemented yet (issue 6)."""

from ..errors import NotYetImplemented
from . import add_parser


def register(sub):
    p = add_parser(sub, "capture", "run a plan on a stage and camera [not implemented yet]", "fieldcal capture --z -100 100 10 --stage sim --camera sim:models/triplet-uncorrected.json --out S")
    p.add_argument("rest", nargs="*", help="(arguments of the future command)")
    p.set_defaults(func=run)


def run(args):
    raise NotYetImplemented("`fieldcal capture` is not implemented yet (tracked in issue 6)",
                            fix="use the stages that exist; see README.md")
