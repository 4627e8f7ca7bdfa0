/* A full disk or a read-only file system under one folder, for the fault tests (LD_PRELOAD).
 *
 * Once the file FAULTFS_TRIGGER exists, every write to a file under FAULTFS_DIR fails with
 * errno FAULTFS_ERRNO (28 ENOSPC: a full disk; 30 EROFS: a read-only file system), as the
 * kernel would fail it: write, pwrite, writev, pwritev, fallocate and ftruncate (growing) return -1;
 * with EROFS, opening a file there for writing, creating, renaming, removing or making a folder
 * fails too (with ENOSPC those still work, as on a real full disk whose inodes are left).
 * Reading is never touched. The calls go to libc's own functions otherwise (dlsym RTLD_NEXT), so
 * Python, sqlite and torch in every process started with LD_PRELOAD=faultfs.so see the fault.
 *
 * Build: cc -shared -fPIC -O2 -o faultfs.so faultfs.c -ldl
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/uio.h>
#include <unistd.h>

static int armed(void) {
    const char *trigger = getenv("FAULTFS_TRIGGER");
    return trigger != NULL && access(trigger, F_OK) == 0;
}

static int fault_errno(void) {
    const char *e = getenv("FAULTFS_ERRNO");
    return e ? atoi(e) : ENOSPC;
}

static int under_dir(const char *path) {
    const char *dir = getenv("FAULTFS_DIR");
    size_t n;
    if (dir == NULL || path == NULL) return 0;
    n = strlen(dir);
    return strncmp(path, dir, n) == 0 && (path[n] == '/' || path[n] == '\0');
}

static int path_hit(const char *path) {
    char full[PATH_MAX];
    if (path == NULL || !armed()) return 0;
    if (path[0] == '/') return under_dir(path);
    if (getcwd(full, sizeof full) == NULL) return 0;
    if (strlen(full) + strlen(path) + 2 > sizeof full) return 0;
    strcat(full, "/");
    strcat(full, path);
    return under_dir(full);
}

static int fd_hit(int fd) {
    char link[64], target[PATH_MAX];
    ssize_t n;
    if (!armed()) return 0;
    snprintf(link, sizeof link, "/proc/self/fd/%d", fd);
    n = readlink(link, target, sizeof target - 1);
    if (n <= 0) return 0;
    target[n] = '\0';
    return under_dir(target);
}

#define REAL(name) static __typeof__(name) *real_##name; if (!real_##name) real_##name = dlsym(RTLD_NEXT, #name)
#define FAIL() do { errno = fault_errno(); return -1; } while (0)

ssize_t write(int fd, const void *buf, size_t count) {
    REAL(write);
    if (count && fd > 2 && fd_hit(fd)) FAIL();
    return real_write(fd, buf, count);
}

ssize_t pwrite(int fd, const void *buf, size_t count, off_t offset) {
    REAL(pwrite);
    if (count && fd_hit(fd)) FAIL();
    return real_pwrite(fd, buf, count, offset);
}

ssize_t pwrite64(int fd, const void *buf, size_t count, off_t offset) {
    REAL(pwrite64);
    if (count && fd_hit(fd)) FAIL();
    return real_pwrite64(fd, buf, count, offset);
}

ssize_t writev(int fd, const struct iovec *iov, int iovcnt) {
    REAL(writev);
    if (fd > 2 && fd_hit(fd)) FAIL();
    return real_writev(fd, iov, iovcnt);
}

ssize_t pwritev(int fd, const struct iovec *iov, int iovcnt, off_t offset) {
    REAL(pwritev);
    if (fd_hit(fd)) FAIL();
    return real_pwritev(fd, iov, iovcnt, offset);
}

int fallocate(int fd, int mode, off_t offset, off_t len) {
    REAL(fallocate);
    if (fd_hit(fd)) FAIL();
    return real_fallocate(fd, mode, offset, len);
}

int posix_fallocate(int fd, off_t offset, off_t len) {
    REAL(posix_fallocate);
    if (fd_hit(fd)) return fault_errno();
    return real_posix_fallocate(fd, offset, len);
}

int ftruncate(int fd, off_t length) {
    struct stat st;
    REAL(ftruncate);
    if (fd_hit(fd) && (fault_errno() == EROFS || (fstat(fd, &st) == 0 && length > st.st_size))) FAIL();
    return real_ftruncate(fd, length);
}

/* ------------------------------------------------------------ a read-only file system: no change at all */
static int ro_hit(const char *path) { return fault_errno() == EROFS && path_hit(path); }

static int writes(int flags) { return (flags & (O_WRONLY | O_RDWR | O_CREAT | O_TRUNC | O_APPEND)) != 0; }

int open(const char *path, int flags, ...) {
    mode_t mode = 0;
    va_list ap;
    REAL(open);
    if (flags & O_CREAT) { va_start(ap, flags); mode = va_arg(ap, mode_t); va_end(ap); }
    if (writes(flags) && ro_hit(path)) FAIL();
    return real_open(path, flags, mode);
}

int open64(const char *path, int flags, ...) {
    mode_t mode = 0;
    va_list ap;
    REAL(open64);
    if (flags & O_CREAT) { va_start(ap, flags); mode = va_arg(ap, mode_t); va_end(ap); }
    if (writes(flags) && ro_hit(path)) FAIL();
    return real_open64(path, flags, mode);
}

int openat(int dirfd, const char *path, int flags, ...) {
    mode_t mode = 0;
    va_list ap;
    REAL(openat);
    if (flags & O_CREAT) { va_start(ap, flags); mode = va_arg(ap, mode_t); va_end(ap); }
    if (writes(flags) && (dirfd == AT_FDCWD || path[0] == '/') && ro_hit(path)) FAIL();
    return real_openat(dirfd, path, flags, mode);
}

int rename(const char *from, const char *to) {
    REAL(rename);
    if (ro_hit(from) || ro_hit(to)) FAIL();
    return real_rename(from, to);
}

int unlink(const char *path) {
    REAL(unlink);
    if (ro_hit(path)) FAIL();
    return real_unlink(path);
}

int mkdir(const char *path, mode_t mode) {
    REAL(mkdir);
    if (ro_hit(path)) FAIL();
    return real_mkdir(path, mode);
}
