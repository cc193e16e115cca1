"""``python -m endomeasure``: the same as the ``endomeasure`` command."""

from endomeasure import interrupts

interrupts.install()  # before the command line loads: a Ctrl-C meanwhile is remembered

from endomeasure.cli import main  # noqa: E402

main()
