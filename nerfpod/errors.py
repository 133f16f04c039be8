"""A user's mistake: the one exception type for it, and the one way every command starts and ends (Command.run):
it reads its command line (absl flags, parse_flags), where a bad flag is such a mistake, loads its config where
it takes one, and ends on a mistake (one sentence, exit 2) or Ctrl-C (one sentence, exit 130)."""
import dataclasses
import faulthandler
import os
import re
import signal
import sys
from typing import Any, Callable, NoReturn, Sequence

from absl import flags

HELP_WORDS = ("-h", "--help", "--helpshort", "--helpfull")
INTERRUPTED_EXIT_CODE = 128 + signal.SIGINT  # 130: a command stopped by Ctrl-C (the shells' convention)


class UserError(Exception):
  """Bad input (data, config, workdir). The message names the problem and the fix."""
  exit_code = 2  # what fail() exits with (2: bad input)
  ends_at_once = False  # fail() ends the process without waiting for its other threads (os._exit)


def fail(problem: "UserError | str", program: str = "nerfpod", code: int | None = None) -> NoReturn:
  """Ends a command on a user's mistake: each of its messages (a ConfigError has several) as one line of
  stderr, `PROGRAM: error: MESSAGE`, whitespace folded, no traceback; then exit `code` (default: the error's
  exit_code, 2: bad input). An error whose `ends_at_once` is set (storage that stopped answering, whose
  clients' threads may never return) ends the process at once, with its output flushed."""
  for message in getattr(problem, "messages", None) or [str(problem)]:
    print(f"{program}: error: {' '.join(str(message).split())}", file=sys.stderr, flush=True)
  code = getattr(problem, "exit_code", 2) if code is None else code
  if getattr(problem, "ends_at_once", False):
    sys.stdout.flush()
    os._exit(code)
  sys.exit(code)


@dataclasses.dataclass(frozen=True)
class Command:
  """A command as every one starts and ends (`run`): its name (`nerfpod bench`, its --help's usage line and the
  name its messages give), the one line of its --help, its absl flags (a flags.FlagValues of its own, or absl's
  FLAGS for a run) with those it requires and an example value of each, whether it takes a `--config` (an
  ml_collections config file flag among its flags, loaded and checked once, by `check`, before the work starts),
  and what its Ctrl-C sentence adds: what the same command does when run again (or a function of the parsed
  flags giving it)."""
  name: str
  about: str
  flag_values: flags.FlagValues
  required: Sequence[str] = ()
  examples: dict[str, str] = dataclasses.field(default_factory=dict)
  check: Callable[[Any], None] | None = None  # takes a --config: what the loaded config must pass (schema.validate)
  after_ctrl_c: str | Callable[[], str] = ""

  def run(self, argv: Sequence[str] | None, work: Callable[..., int | None]) -> None:
    """The command: parses `argv` (the words after the command's name; None: sys.argv[1:]) into its flags
    (parse_flags: --help, one sentence and exit 2 for a bad flag), loads its config where it takes one, then
    `work()` (`work(config)`), whose result is the exit code (None or 0: return). A UserError anywhere is its one
    sentence and exit 2 (`fail`); Ctrl-C outside a handler of its own (training's steps save first:
    run/preemption.py) is `nerfpod: interrupted` with `after_ctrl_c`, exit 130."""
    _start_process()
    try:
      parse_flags(self.name, self.about, self.flag_values, sys.argv[1:] if argv is None else argv, self.required,
                  self.examples)
      code = work() if self.check is None else work(self._config())
    except UserError as e:
      fail(e)
    except KeyboardInterrupt:
      after = self.after_ctrl_c() if callable(self.after_ctrl_c) else self.after_ctrl_c
      print(f"nerfpod: interrupted{'; ' + after if after else ''}", file=sys.stderr, flush=True)
      sys.exit(INTERRUPTED_EXIT_CODE)
    if code:
      sys.exit(code)

  def _config(self):
    """The --config flag's value (the file's get_config(arg), the overrides applied), checked: a file that does
    not exist or does not load is one sentence, as is each mistake `check` finds (UserError)."""
    from ml_collections import config_flags
    path = config_flags.get_config_filename(self.flag_values["config"]).split(":")[0]
    if not os.path.isfile(path):
      raise UserError(f"the --config file {path} does not exist (a relative path is from the current folder, "
                      f"{os.getcwd()}).")
    try:
      config = self.flag_values["config"].value
      config.keys()  # the value is a lazy proxy until first touched
    except UserError:
      raise
    except (OSError, AttributeError, KeyError, TypeError, ValueError, SyntaxError, ImportError) as e:
      raise UserError(f"could not load the --config file {path} ({' '.join(str(e).split())[:300]}).") from None
    self.check(config)
    return config


def _start_process() -> None:
  """What absl's app.run did for a command, once per process: absl's log handler on Python's logging (its
  format, and --verbosity's level, for nerfpod's and its libraries' log lines) and, where nothing has yet,
  Python's fault handler (a crash in native code prints every thread's stack)."""
  from absl import logging
  logging.use_absl_handler()
  if not faulthandler.is_enabled():
    try:
      faulthandler.enable()
    except (AttributeError, ValueError, OSError):  # a stderr without a file descriptor (a test's capture)
      pass


def parse_flags(command: str, about: str, flag_values: flags.FlagValues, args: Sequence[str],
                required: Sequence[str] = (), examples: dict[str, str] | None = None) -> None:
  """Parses `args` (the words after `command`, e.g. "nerfpod view") into `flag_values`: the one way every
  subcommand reads its command line. -h/--help prints `about` (one line) and the command's own flags (absl's
  help text; --helpfull: absl's flags too), exit 0. Any mistake (an unknown flag, a bad value, a `required`
  flag left out, a word that is no flag) is one sentence naming the flag and a valid value (`examples`: flag ->
  a value, else its default), `nerfpod: error: ...`, exit 2. The flags parse from their defaults each time."""
  args = list(args)
  words = args[:args.index("--")] if "--" in args else args
  if any(word in HELP_WORDS for word in words):
    print(flags_help(command, about, flag_values, everything="--helpfull" in words))
    sys.exit(0)
  examples = examples or {}
  flag_values.unparse_flags()
  if any(type(flag).__module__.startswith("ml_collections") for flag in map(flag_values.__getitem__, flag_values)):
    sys.argv[:] = [command, *args]  # ml_collections reads a --config's overrides off sys.argv
  see = f"`{command} --help` lists the flags"
  try:
    rest = flag_values([command, *args])[1:]
  except UserError as e:  # raised by a config file's get_config (e.g. an unknown argument after the colon)
    fail(e)
  except flags.UnrecognizedFlagError as e:
    fail(f"unknown flag --{e.flagname}; {command} takes {', '.join(_own_flags(flag_values))} (`{command} --help` "
         f"says what each does).")
  except flags.IllegalFlagValueError as e:
    fail(_bad_value(str(e), flag_values, examples, see))
  except flags.Error as e:  # e.g. a flag given last without its value
    named = re.search(r"--([\w.]+)", str(e))
    example = examples.get(named.group(1)) if named else None
    fail(f"{_fold(str(e))}; {f'e.g. --{named.group(1)}={example}' if example else see}.")
  except (AttributeError, KeyError, TypeError, ValueError, OSError, SyntaxError, ImportError) as e:
    if "does not take an argument" in str(e):  # absl: --noflag=value
      name = str(e).split("=")[0].removeprefix("--no")
      fail(f"{_fold(str(e))}; a yes/no flag is given as --{name} or --no{name}.")
    if isinstance(e, (AttributeError, KeyError)):
      unknown = _unknown_override(str(e), args)
      if unknown:
        fail(unknown)
    fail(f"bad --config file or override ({_fold(str(e))}); the config file's fields say what each override "
         f"takes, and {see}.")  # ml_collections: a config file or override that does not apply
  if rest:
    fail(f"unexpected arguments: {' '.join(rest)} (flags take the form --name=value; {see}).")
  missing = [name for name in required if not flag_values[name].present]
  if missing:
    fail(f"{' and '.join('--' + n for n in missing)} {'is' if len(missing) == 1 else 'are'} required, e.g. "
         f"{' '.join(f'--{n}={examples[n]}' for n in missing)} ({see}).")
  if flag_values is not flags.FLAGS and not flags.FLAGS.is_parsed():
    flags.FLAGS.mark_as_parsed()  # absl (its logging) reads its own flags: their defaults


def flags_help(command: str, about: str, flag_values: flags.FlagValues, everything: bool = False) -> str:
  """The command's --help: its usage, `about` and its flags as absl describes them (`everything`: absl's own
  flags too, under the module that defines each)."""
  modules = flag_values.flags_by_module_dict()
  if everything:
    text = flag_values.get_help(prefix="  ")
  else:
    text = "\n".join(flag_values.module_help(m).strip("\n").split("\n", 1)[1] for m in modules
                     if not m.startswith("absl"))
  more = "" if everything else "\n\n(--helpfull: absl's own flags too)"
  return f"usage: {command} [flags]\n\n{about}\n\nflags:\n{text}{more}"


def _own_flags(flag_values: flags.FlagValues) -> list[str]:
  return [f"--{name}" for module, defined in flag_values.flags_by_module_dict().items()
          if not module.startswith("absl") for name in sorted(f.name for f in defined)]


def _unknown_override(message: str, args: Sequence[str]) -> str | None:
  """The sentence for a --config.A.B.C=... override naming a field the config lacks (ml_collections' KeyError
  or AttributeError names only the last part, and may suggest a field), with its whole path; None where no
  override names it."""
  named = re.search(r"\w+", message)
  suggestion = re.search(r'Did you mean "(\w+)" instead of "(\w+)"', message)
  name = suggestion.group(2) if suggestion else named.group(0) if named else None
  for arg in args:
    path = arg.removeprefix("--").split("=", 1)[0]
    parts = path.split(".")
    if parts[0] == "config" and name in parts[1:]:
      section = ".".join(parts[1:parts.index(name, 1)])
      hint = f" (did you mean {'.'.join(filter(None, [section, suggestion.group(1)]))}?)" if suggestion else ""
      return (f"--{path}: {f'config section {section}' if section else 'the config'} has no field {name!r}{hint}; "
              f"`python -m nerfpod.schema` lists every field, its values and what it means.")
  return None


def _fold(message: str) -> str:
  """absl's and ml_collections' messages on one line, with their quoting undone."""
  return " ".join(message.replace("\\n", " ").replace("\\'", "'").replace("''", "'").split()).rstrip(".")


def _bad_value(message: str, flag_values: flags.FlagValues, examples: dict[str, str], see: str) -> str:
  """absl's `flag --NAME=VALUE: REASON` as one sentence that ends with a valid value."""
  match = re.match(r"flag --([^=]+)=(.*?): (.*)", _fold(message), re.S)
  if not match:
    return f"{_fold(message)}; {see}."
  name, value, reason = match.groups()
  example = examples.get(name)
  flag = flag_values[name] if name in flag_values else None
  if flag is not None and isinstance(flag.value, list) and value.startswith("["):  # a validator's refusal
    value = flag.serializer.serialize(flag.value)
  if example is None and flag is not None and flag.default is not None and not flag.boolean:
    example = flag.serializer.serialize(flag.default) if flag.serializer else str(flag.default)
  if flag is not None and flag.boolean:
    hint = f"a yes/no flag is given as --{name} or --no{name}"
    reason = "not true or false"
  elif example:
    hint = f"e.g. --{name}={example}"
  elif name.startswith("config."):
    hint = "give a value of the type the config file's field holds"
  elif flag is not None and flag.parser.syntactic_help:
    hint = f"--{name} takes {flag.parser.syntactic_help} ({see})"
  else:
    hint = see
  return f"--{name}={value}: {reason}; {hint}."
