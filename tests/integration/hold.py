"""Holding a writer mid-way, whatever the machine's speed: the file-system calls of one class
(write, sync, rename, mkdir, create, unlink, link) under a directory are counted by the LD_PRELOAD
library tests/fault/fault_inject.c, and call n waits while the gate file holds a number below n.

    hold = Hold(lib, prefix="/data/prism", cls="create", gate="/work/gate")
    proc = subprocess.Popen([...], env=hold.env())    # no gate yet: every call goes
    n = hold.let_through(hold.calls())                 # from now on the next call waits
    ...                                                # start the writer's job
    hold.wait_held(n + 1, ended=lambda: job_is_final())  # the writer is stopped there
    ...                                                # look at it while nothing moves
    hold.let_through(n + 50)                           # 50 more calls go, the next waits
    hold.release()                                     # every call goes (also in a finally:)

A test that waits for a state here polls for it with a generous deadline; it never sleeps for a
time instead, so the verdict does not depend on how fast the machine is.
"""

import os
import time

from harness import fault_env


class Hold:
    def __init__(self, lib, prefix, cls, gate):
        """The gate starts open (no file); every counted call is traced to `gate`.trace."""
        self.lib = lib
        self.prefix = os.path.abspath(prefix)
        self.cls = cls
        self.gate = os.path.abspath(gate)
        self.trace = self.gate + ".trace"
        self.allowed = None
        for name in os.listdir(os.path.dirname(self.gate)):
            if name.startswith(os.path.basename(self.gate)):
                os.remove(os.path.join(os.path.dirname(self.gate), name))

    def env(self, base=None):
        """The environment that preloads the library into a process (`base`: os.environ)."""
        return fault_env(self.lib, self.prefix, base, hold=self.cls, gate=self.gate,
                         trace=self.trace)

    def calls(self):
        """The calls of the class counted so far (from the trace)."""
        n = 0
        if os.path.exists(self.trace):
            with open(self.trace) as f:
                for line in f:
                    fields = line.split(" ", 3)
                    if len(fields) == 4 and fields[1] == self.cls:
                        n = max(n, int(fields[2]))
        return n

    def let_through(self, allowed):
        """Calls 1..allowed go on; call allowed + 1 and later ones wait. Atomic (rename), so the
        library never reads a half-written number. Returns `allowed`."""
        self.allowed = allowed
        temporary = self.gate + ".new"
        with open(temporary, "w") as f:
            f.write("%d\n" % allowed)
        os.replace(temporary, self.gate)
        return allowed

    def release(self):
        """Every call goes on, now and later. Idempotent."""
        self.allowed = None
        try:
            os.remove(self.gate)
        except FileNotFoundError:
            pass

    def held(self, n):
        """The path of call n when it is waiting now, else None."""
        try:
            with open("%s.held-%d" % (self.gate, n)) as f:
                return f.read().strip()
        except FileNotFoundError:
            return None

    def wait_held(self, n, ended=lambda: False, timeout=300):
        """Polls until call n waits at the gate (returns its path) or ended() says the writer
        will make no such call (returns None). Raises AssertionError after `timeout` seconds, a
        bound far above what any machine needs, so it only ends a test that would hang."""
        deadline = time.monotonic() + timeout
        while True:
            path = self.held(n)
            if path is not None:
                return path
            if ended():
                return None
            if time.monotonic() > deadline:
                raise AssertionError("call %d of class %s under %s did not reach the gate "
                                     "within %d s" % (n, self.cls, self.prefix, timeout))
            time.sleep(0.01)  # the poll interval


def poll(condition, timeout=300, interval=0.02):
    """condition()'s first true value, polled until `timeout` seconds have passed (then its last
    value). For conditions a correct program reaches on any machine."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value or time.monotonic() > deadline:
            return value
        time.sleep(interval)
