"""Run the soulctl command line in-process, as the tests of its commands do."""

from soulctl.cli.app import main


def run(argv, capsys):
    """(exit status, stdout, stderr) of ``soulctl argv`` (paths and numbers as text)."""
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err
