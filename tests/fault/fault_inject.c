// An LD_PRELOAD library that fails one chosen file-system call of a process, for the fault sweep
// (tests/integration/fault_sweep_test.py), or holds a process at a chosen call until the test lets
// it go on (tests/integration/hold.py), so that a test sees a job mid-way whatever the machine's
// speed. Only calls on paths below VSM_FAULT_PREFIX count (for
// calls on a descriptor: the path the descriptor was opened with, read from /proc/self/fd), so the
// process's sockets, logs and libraries are never touched.
//
// Calls are counted per class:
//   write   write, pwrite, pwrite64, writev, pwritev
//   sync    fsync, fdatasync, syncfs
//   rename  rename, renameat, renameat2
//   mkdir   mkdir, mkdirat
//   create  open, open64, openat, openat64, creat with O_CREAT
//   unlink  unlink, unlinkat, rmdir, remove
//   link    link, linkat (the path of the new name counts)
//   read    open, open64, openat, openat64 for reading only (no O_CREAT, O_RDONLY); counted only
//           when VSM_FAULT_HOLD or VSM_FAULT_CLASS names it, so that the traces of the other
//           classes stay as they were (tests/integration/costly_reads_test.py holds a revision
//           read with it)
//
// Environment:
//   VSM_FAULT_PREFIX  absolute directory; nothing happens without it
//   VSM_FAULT_TRACE   file: every counted call is appended as "<seq> <class> <n> <path>", where
//                     <seq> counts all classes and <n> this class, both from 1
//   VSM_FAULT_CLASS   the class whose VSM_FAULT_N-th call fails (once) with VSM_FAULT_ERRNO
//                     ("EIO", "ENOSPC" or "ENOENT"; default EIO); the call is not made
//   VSM_FAULT_APPLIED "1": for the rename class, the failing call is made first and then reported
//                     failed (as a retransmitted rename over NFS reports ENOENT after the server
//                     applied it)
//   VSM_FAULT_REPORT  file: the injected fault is appended as "<class> <n> <errno> <path>"
//   VSM_FAULT_ARM     file: while it exists and holds "<class> <errno>" (e.g. "create ENOSPC";
//                     errno EIO, ENOSPC or ENOENT), the next call of that class fails with that
//                     errno (once: the library removes the file), so that a test arms a fault in
//                     a running process at a moment of its choosing
//                     (tests/integration/nemesis_test.py); reported as VSM_FAULT_CLASS's faults are
//   VSM_FAULT_HOLD    a class whose calls can be held, so that a test stops a writer at a chosen
//   VSM_FAULT_GATE    point, looks at it there, and lets it go on (with or without a fault):
//                     call n of the class waits, before it is made, while the file
//                     VSM_FAULT_GATE exists and holds a number below n (the calls let through;
//                     a file without a number counts as 0). While it waits,
//                     "<VSM_FAULT_GATE>.held-<n>" exists and holds the call's path. The test
//                     replaces the gate (rename) with a larger number, or removes it, to let
//                     calls through. Without a gate file no call waits.
//
// Written in C with raw syscalls for its own output, so it never recurses into itself.
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

enum { kWrite, kSync, kRename, kMkdir, kCreate, kUnlink, kLink, kRead, kClasses };
static const char* const kClassNames[kClasses] = {"write",  "sync",   "rename", "mkdir",
                                                  "create", "unlink", "link",   "read"};

static char prefix[PATH_MAX];
static size_t prefixLength;
static char tracePath[PATH_MAX];
static char reportPath[PATH_MAX];
static int faultClass = -1;
static long faultN;
static int faultErrno = EIO;
static int faultApplied;
static char gatePath[PATH_MAX - 32];
static char armPath[PATH_MAX];
static int holdClass = -1;
static unsigned long counts[kClasses];
static unsigned long sequence;
static pthread_mutex_t mutex = PTHREAD_MUTEX_INITIALIZER;  // guards counts, sequence, output

__attribute__((constructor)) static void setup(void) {
  const char* p = getenv("VSM_FAULT_PREFIX");
  if (p == NULL || p[0] != '/' || strlen(p) >= sizeof prefix) {
    return;
  }
  strcpy(prefix, p);
  prefixLength = strlen(prefix);
  while (prefixLength > 1 && prefix[prefixLength - 1] == '/') {
    prefix[--prefixLength] = '\0';
  }
  const char* t = getenv("VSM_FAULT_TRACE");
  if (t != NULL && strlen(t) < sizeof tracePath) {
    strcpy(tracePath, t);
  }
  const char* r = getenv("VSM_FAULT_REPORT");
  if (r != NULL && strlen(r) < sizeof reportPath) {
    strcpy(reportPath, r);
  }
  const char* c = getenv("VSM_FAULT_CLASS");
  const char* n = getenv("VSM_FAULT_N");
  if (c != NULL && n != NULL) {
    for (int i = 0; i < kClasses; ++i) {
      if (strcmp(c, kClassNames[i]) == 0) {
        faultClass = i;
      }
    }
    faultN = strtol(n, NULL, 10);
  }
  const char* h = getenv("VSM_FAULT_HOLD");
  const char* g = getenv("VSM_FAULT_GATE");
  if (h != NULL && g != NULL && g[0] != '\0' && strlen(g) < sizeof gatePath) {
    for (int i = 0; i < kClasses; ++i) {
      if (strcmp(h, kClassNames[i]) == 0) {
        holdClass = i;
      }
    }
    strcpy(gatePath, g);
  }
  const char* e = getenv("VSM_FAULT_ERRNO");
  if (e != NULL && strcmp(e, "ENOSPC") == 0) {
    faultErrno = ENOSPC;
  }
  if (e != NULL && strcmp(e, "ENOENT") == 0) {
    faultErrno = ENOENT;
  }
  const char* arm = getenv("VSM_FAULT_ARM");
  if (arm != NULL && strlen(arm) < sizeof armPath) {
    strcpy(armPath, arm);
  }
  const char* a = getenv("VSM_FAULT_APPLIED");
  faultApplied = a != NULL && strcmp(a, "1") == 0;
}

static void appendLine(const char* file, const char* line) {
  const int fd =
      (int)syscall(SYS_openat, AT_FDCWD, file, O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
  if (fd >= 0) {
    syscall(SYS_write, fd, line, strlen(line));
    syscall(SYS_close, fd);
  }
}

static int below(const char* path) {
  return strncmp(path, prefix, prefixLength) == 0 &&
         (path[prefixLength] == '/' || path[prefixLength] == '\0');
}

/// The absolute form of `path` relative to `dirfd` (lexically; enough for our prefixes).
static void absolute(int dirfd, const char* path, char* out, size_t size) {
  if (path[0] == '/') {
    snprintf(out, size, "%s", path);
    return;
  }
  char base[PATH_MAX];
  if (dirfd == AT_FDCWD) {
    if (syscall(SYS_getcwd, base, sizeof base) < 0) {
      base[0] = '\0';
    }
  } else {
    char link[64];
    snprintf(link, sizeof link, "/proc/self/fd/%d", dirfd);
    const ssize_t n = readlink(link, base, sizeof base - 1);
    base[n > 0 ? n : 0] = '\0';
  }
  snprintf(out, size, "%s/%s", base, path);
}

static void pathOfFd(int fd, char* out, size_t size) {
  char link[64];
  snprintf(link, sizeof link, "/proc/self/fd/%d", fd);
  const ssize_t n = readlink(link, out, size - 1);
  out[n > 0 ? n : 0] = '\0';
}

/// The number of calls the gate lets through; -1 when there is no gate file.
static long gateAllows(void) {
  const int fd = (int)syscall(SYS_openat, AT_FDCWD, gatePath, O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    return -1;
  }
  char text[32];
  const long n = (long)syscall(SYS_read, fd, text, sizeof text - 1);
  syscall(SYS_close, fd);
  text[n > 0 ? n : 0] = '\0';
  return strtol(text, NULL, 10);
}

/// The errno armed for class `c` by VSM_FAULT_ARM's file, which is then removed (so it fires
/// once); 0 when none is armed for it. Called under the mutex.
static int armed(int c) {
  if (armPath[0] == '\0') {
    return 0;
  }
  const int fd = (int)syscall(SYS_openat, AT_FDCWD, armPath, O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    return 0;
  }
  char text[64];
  const long n = (long)syscall(SYS_read, fd, text, sizeof text - 1);
  syscall(SYS_close, fd);
  text[n > 0 ? n : 0] = '\0';
  const size_t length = strlen(kClassNames[c]);
  if (strncmp(text, kClassNames[c], length) != 0 || text[length] != ' ') {
    return 0;
  }
  const char* name = text + length + 1;
  const int e = strncmp(name, "ENOSPC", 6) == 0   ? ENOSPC
                : strncmp(name, "ENOENT", 6) == 0 ? ENOENT
                                                  : EIO;
  syscall(SYS_unlinkat, AT_FDCWD, armPath, 0);
  return e;
}

/// Waits while the gate holds call `n` (see VSM_FAULT_GATE), showing it in "<gate>.held-<n>".
static void hold(unsigned long n, const char* path) {
  const long allows = gateAllows();
  if (allows < 0 || (unsigned long)allows >= n) {
    return;
  }
  char held[PATH_MAX];
  snprintf(held, sizeof held, "%s.held-%lu", gatePath, n);
  char line[PATH_MAX + 1];
  snprintf(line, sizeof line, "%s\n", path);
  const int fd =
      (int)syscall(SYS_openat, AT_FDCWD, held, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd >= 0) {
    syscall(SYS_write, fd, line, strlen(line));
    syscall(SYS_close, fd);
  }
  for (;;) {
    const struct timespec pause = {0, 2 * 1000 * 1000};
    nanosleep(&pause, NULL);
    const long now = gateAllows();
    if (now < 0 || (unsigned long)now >= n) {
      break;
    }
  }
  syscall(SYS_unlinkat, AT_FDCWD, held, 0);
}

/// Counts a call on `path` of class `c` (held first when the gate says so, see VSM_FAULT_GATE);
/// true when this call is the one to fail (errno is set).
static int fault(int c, const char* path) {
  if (prefixLength == 0 || !below(path)) {
    return 0;
  }
  pthread_mutex_lock(&mutex);
  const unsigned long n = ++counts[c];
  const unsigned long seq = ++sequence;
  const int error = c == faultClass && (long)n == faultN ? faultErrno : armed(c);
  const int inject = error != 0;
  char line[PATH_MAX + 96];
  if (tracePath[0] != '\0') {
    snprintf(line, sizeof line, "%lu %s %lu %s\n", seq, kClassNames[c], n, path);
    appendLine(tracePath, line);
  }
  if (inject && reportPath[0] != '\0') {
    snprintf(line, sizeof line, "%s %lu %s %s\n", kClassNames[c], n,
             error == ENOSPC   ? "ENOSPC"
             : error == ENOENT ? "ENOENT"
                               : "EIO",
             path);
    appendLine(reportPath, line);
  }
  pthread_mutex_unlock(&mutex);
  if (c == holdClass) {
    hold(n, path);  // not under the mutex: the process's other calls go on
  }
  if (inject) {
    errno = error;
  }
  return inject;
}

static int faultAt(int c, int dirfd, const char* path) {
  if (prefixLength == 0 || path == NULL) {
    return 0;
  }
  if (c == kRead && holdClass != kRead && faultClass != kRead) {
    return 0;  // opt-in (see the class list above)
  }
  char full[PATH_MAX];
  absolute(dirfd, path, full, sizeof full);
  return fault(c, full);
}

static int faultFd(int c, int fd) {
  if (prefixLength == 0) {
    return 0;
  }
  char path[PATH_MAX];
  pathOfFd(fd, path, sizeof path);
  return fault(c, path);
}

#define NEXT(name) ((__typeof__(&name))dlsym(RTLD_NEXT, #name))

ssize_t write(int fd, const void* buf, size_t count) {
  if (faultFd(kWrite, fd)) {
    return -1;
  }
  return NEXT(write)(fd, buf, count);
}

ssize_t pwrite(int fd, const void* buf, size_t count, off_t offset) {
  if (faultFd(kWrite, fd)) {
    return -1;
  }
  return NEXT(pwrite)(fd, buf, count, offset);
}

ssize_t pwrite64(int fd, const void* buf, size_t count, off64_t offset) {
  if (faultFd(kWrite, fd)) {
    return -1;
  }
  return NEXT(pwrite64)(fd, buf, count, offset);
}

ssize_t writev(int fd, const struct iovec* iov, int iovcnt) {
  if (faultFd(kWrite, fd)) {
    return -1;
  }
  return NEXT(writev)(fd, iov, iovcnt);
}

ssize_t pwritev(int fd, const struct iovec* iov, int iovcnt, off_t offset) {
  if (faultFd(kWrite, fd)) {
    return -1;
  }
  return NEXT(pwritev)(fd, iov, iovcnt, offset);
}

int fsync(int fd) {
  if (faultFd(kSync, fd)) {
    return -1;
  }
  return NEXT(fsync)(fd);
}

int fdatasync(int fd) {
  if (faultFd(kSync, fd)) {
    return -1;
  }
  return NEXT(fdatasync)(fd);
}

int syncfs(int fd) {
  if (faultFd(kSync, fd)) {
    return -1;
  }
  return NEXT(syncfs)(fd);
}

int rename(const char* from, const char* to) {
  if (faultAt(kRename, AT_FDCWD, to)) {
    if (faultApplied) {
      const int reported = errno;
      NEXT(rename)(from, to);
      errno = reported;
    }
    return -1;
  }
  return NEXT(rename)(from, to);
}

int renameat(int fromDir, const char* from, int toDir, const char* to) {
  if (faultAt(kRename, toDir, to)) {
    if (faultApplied) {
      const int reported = errno;
      NEXT(renameat)(fromDir, from, toDir, to);
      errno = reported;
    }
    return -1;
  }
  return NEXT(renameat)(fromDir, from, toDir, to);
}

int renameat2(int fromDir, const char* from, int toDir, const char* to, unsigned int flags) {
  if (faultAt(kRename, toDir, to)) {
    if (faultApplied) {
      const int reported = errno;
      NEXT(renameat2)(fromDir, from, toDir, to, flags);
      errno = reported;
    }
    return -1;
  }
  return NEXT(renameat2)(fromDir, from, toDir, to, flags);
}

int link(const char* from, const char* to) {
  if (faultAt(kLink, AT_FDCWD, to)) {
    return -1;
  }
  return NEXT(link)(from, to);
}

int linkat(int fromDir, const char* from, int toDir, const char* to, int flags) {
  if (faultAt(kLink, toDir, to)) {
    return -1;
  }
  return NEXT(linkat)(fromDir, from, toDir, to, flags);
}

int mkdir(const char* path, mode_t mode) {
  if (faultAt(kMkdir, AT_FDCWD, path)) {
    return -1;
  }
  return NEXT(mkdir)(path, mode);
}

int mkdirat(int dirfd, const char* path, mode_t mode) {
  if (faultAt(kMkdir, dirfd, path)) {
    return -1;
  }
  return NEXT(mkdirat)(dirfd, path, mode);
}

static int readOnly(int flags) {
  return (flags & (O_CREAT | __O_TMPFILE)) == 0 && (flags & O_ACCMODE) == O_RDONLY;
}

static mode_t modeOf(int flags, va_list args) {
  return (flags & (O_CREAT | __O_TMPFILE)) != 0 ? (mode_t)va_arg(args, int) : 0;
}

/// The mode argument of the open(2) being wrapped, whose last named parameter is `flags`.
#define OPEN_MODE(flags)                               \
  __extension__({                                      \
    va_list modeArgs;                                  \
    va_start(modeArgs, flags);                         \
    const mode_t modeOfCall = modeOf(flags, modeArgs); \
    va_end(modeArgs);                                  \
    modeOfCall;                                        \
  })

/// Whether an open(2) of `path` (relative to `dirfd`) with `flags` fails here: a create's fault
/// (O_CREAT), or a read's (read-only).
static int openFault(int dirfd, const char* path, int flags) {
  if ((flags & O_CREAT) != 0 && faultAt(kCreate, dirfd, path)) {
    return 1;
  }
  return readOnly(flags) && faultAt(kRead, dirfd, path);
}

int open(const char* path, int flags, ...) {
  const mode_t mode = OPEN_MODE(flags);
  return openFault(AT_FDCWD, path, flags) ? -1 : NEXT(open)(path, flags, mode);
}

int open64(const char* path, int flags, ...) {
  const mode_t mode = OPEN_MODE(flags);
  return openFault(AT_FDCWD, path, flags) ? -1 : NEXT(open64)(path, flags, mode);
}

int openat(int dirfd, const char* path, int flags, ...) {
  const mode_t mode = OPEN_MODE(flags);
  return openFault(dirfd, path, flags) ? -1 : NEXT(openat)(dirfd, path, flags, mode);
}

int openat64(int dirfd, const char* path, int flags, ...) {
  const mode_t mode = OPEN_MODE(flags);
  return openFault(dirfd, path, flags) ? -1 : NEXT(openat64)(dirfd, path, flags, mode);
}

int creat(const char* path, mode_t mode) {
  if (faultAt(kCreate, AT_FDCWD, path)) {
    return -1;
  }
  return NEXT(creat)(path, mode);
}

int unlink(const char* path) {
  if (faultAt(kUnlink, AT_FDCWD, path)) {
    return -1;
  }
  return NEXT(unlink)(path);
}

int unlinkat(int dirfd, const char* path, int flags) {
  if (faultAt(kUnlink, dirfd, path)) {
    return -1;
  }
  return NEXT(unlinkat)(dirfd, path, flags);
}

int rmdir(const char* path) {
  if (faultAt(kUnlink, AT_FDCWD, path)) {
    return -1;
  }
  return NEXT(rmdir)(path);
}

int remove(const char* path) {
  if (faultAt(kUnlink, AT_FDCWD, path)) {
    return -1;
  }
  return NEXT(remove)(path);
}
