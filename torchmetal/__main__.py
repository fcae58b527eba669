from torchmetal.cli import run

run()
