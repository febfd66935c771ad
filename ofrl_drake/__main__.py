"""``python -m ofrl_drake`` is the ``ofrl-drake`` command.

:func:`console` is also the entry point of the ``ofrl-drake`` script. It
imports the command-line module inside a ``try``, so a SIGINT that lands while
Python is still importing gives the same one line and exit code 130 as one
that lands later (:func:`ofrl_drake.cli.main` handles those).
"""

import sys


def console() -> int:
    """Run the ``ofrl-drake`` command with ``sys.argv``; return its exit code."""
    try:
        from ofrl_drake.cli import main
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted; no output written\n")
        return 130
    return main()


if __name__ == "__main__":
    sys.exit(console())
