"""The one exception type for a user's mistake: printed as one sentence, no stack trace."""


class UserError(Exception):
  """Bad input (data, config, workdir). The message names the problem and the fix."""
