"""``python -m endomeasure``: the same as the ``endomeasure`` command."""

from endomeasure.cli import main

main()
