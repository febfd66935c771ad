"""``python -m ofrl_drake`` is the ``ofrl-drake`` command.

:func:`console` is also the entry point of the ``ofrl-drake`` script. It
imports the command-line module inside a ``try``, so a SIGINT that lands while
Python is still importing gives the same one line and exit code 130 as one
that lands later (:func:`ofrl_drake.cli.main` handles those).
"""

import signal
import sys


def console() -> int:
    """Run the ``ofrl-drake`` command with ``sys.argv``; return its exit code.

    Once the command has returned, its exit code stands: SIGINT is ignored
    while Python shuts down, where a Ctrl-C printed a ``KeyboardInterrupt``
    traceback from an ``atexit`` callback and could end the process without
    the code.
    """
    try:
        from ofrl_drake.cli import main
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted; no output written\n")
        return 130
    code = main()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return code


if __name__ == "__main__":
    sys.exit(console())
