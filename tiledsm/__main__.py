from tiledsm.cli import run

run()
