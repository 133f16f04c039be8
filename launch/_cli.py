"""What the launch scripts share: splitting their own options from the arguments they forward."""


def split_forwarded(argv: list[str]) -> tuple[list[str], list[str]]:
  """(launcher options, nerfpod.main arguments): the two sides of the first `--`."""
  if "--" not in argv:
    return argv, []
  cut = argv.index("--")
  return argv[:cut], argv[cut + 1:]
