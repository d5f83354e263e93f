import atexit
import os
import sys

from .run.supervise import PARENT_ENV, die_with_parent, supervise, wanted

if os.environ.get(PARENT_ENV):  # a supervised run: it ends with its supervisor (killed, say)
    die_with_parent(int(os.environ.pop(PARENT_ENV)))
if wanted(sys.argv[1:]):
    # `bench run` runs in a child process that this one restarts after a backend kills it
    # (bench/run/supervise.py); nothing heavy is imported here
    code = supervise(sys.argv[1:])
else:
    from .commands import main

    code = main()
# The command is over and everything it writes is written and closed; what is left is the
# interpreter's teardown of torch, jax, numba, Warp and Mitsuba (a full collection of ~750,000
# objects and every module's cleanup: 1–2 s after a quick run, measured).  Run the exit handlers
# the libraries registered (multiprocessing's, jax's, logging's, file locks', weakref finalizers)
# as a normal exit would, flush, and end the process without the teardown.
atexit._run_exitfuncs()
sys.stdout.flush()
sys.stderr.flush()
if code is not None and not isinstance(code, int):  # as SystemExit(code) would: printed, status 1
    print(code, file=sys.stderr, flush=True)
os._exit(0 if code is None else code if isinstance(code, int) else 1)
