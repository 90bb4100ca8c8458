/*
 * Loaded into QEMU by the whole-interrupt bench (`LD_PRELOAD`, tests/irq_bench.rs): QEMU
 * line-buffers its log (`-d … -D FILE`) and flushes it after every line, so a traced
 * instruction costs a write(2) — most of QEMU's time on a trace of hundreds of millions of
 * lines. The file named by TWINSTACK_TRACE_FILE gets a 16 KiB buffer instead, written when it
 * is full and at exit (the first file of that name QEMU opens); every other stream is left as
 * QEMU sets it. What QEMU writes is unchanged, only how often.
 *
 * 16 KiB is a quarter of a pipe's 64 KiB: QEMU fills its next buffer while the bench reads
 * the last. A buffer as large as the pipe makes each wait for the other (1 MiB: the bench took
 * 7 min 33 s, against 5 min 53 s with glibc's own 4 KiB).
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static FILE *trace;

typedef FILE *(*open_fn)(const char *, const char *);
typedef int (*setvbuf_fn)(FILE *, char *, int, size_t);
typedef int (*fflush_fn)(FILE *);

static int real_setvbuf(FILE *f, char *buf, int mode, size_t size)
{
    static setvbuf_fn real;
    if (!real)
        real = (setvbuf_fn)dlsym(RTLD_NEXT, "setvbuf");
    return real(f, buf, mode, size);
}

static FILE *opened(FILE *f, const char *path)
{
    const char *wanted = getenv("TWINSTACK_TRACE_FILE");
    if (f && !trace && wanted && strcmp(path, wanted) == 0) {
        /* glibc ignores the size of a buffer it is to allocate itself (it takes the file's
         * block size, 4 KiB for a FIFO): the buffer is given, and lives as long as QEMU. */
        static char buffer[16 << 10];
        trace = f;
        real_setvbuf(f, buffer, _IOFBF, sizeof buffer);
    }
    return f;
}

FILE *fopen64(const char *path, const char *mode)
{
    static open_fn real;
    if (!real)
        real = (open_fn)dlsym(RTLD_NEXT, "fopen64");
    return opened(real(path, mode), path);
}

FILE *fopen(const char *path, const char *mode)
{
    static open_fn real;
    if (!real)
        real = (open_fn)dlsym(RTLD_NEXT, "fopen");
    return opened(real(path, mode), path);
}

int setvbuf(FILE *f, char *buf, int mode, size_t size)
{
    if (f && f == trace)
        return 0;
    return real_setvbuf(f, buf, mode, size);
}

int fflush(FILE *f)
{
    static fflush_fn real;
    if (f && f == trace)
        return 0;
    if (!real)
        real = (fflush_fn)dlsym(RTLD_NEXT, "fflush");
    return real(f);
}
