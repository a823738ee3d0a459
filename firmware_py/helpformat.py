"""`--help` that shows every default: the formatter of qnav-robot and qnav-sim.

argparse's ArgumentDefaultsHelpFormatter also prints "(default: None)" and repeats defaults a help
text already states; this one appends "(default: X)" only when there is a real default the text does
not mention, and keeps descriptions and epilogs as written (RawDescription).
"""

from __future__ import annotations

import argparse


class DefaultsHelpFormatter(argparse.RawDescriptionHelpFormatter):
    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (default is None or default is False or default is argparse.SUPPRESS or "default" in text
                or action.option_strings == [] or isinstance(action, argparse._HelpAction)):
            return action.help
        return f"{text} (default: %(default)s)" if text else "(default: %(default)s)"
