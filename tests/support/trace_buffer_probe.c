/*
 * The trace buffer's test (`the_trace_buffer_holds_qemu_s_log_until_it_is_full`,
 * tests/irq_bench.rs): opens the file named by its first argument as QEMU opens its log
 * (fopen64, line-buffered, flushed after every line), writes 200 lines (12 400 bytes, less
 * than the trace buffer's 16 KiB and more than glibc's own 4 KiB), and prints the file's size
 * before closing it. Without the trace buffer every line is written at once; with it, for the
 * file named by TWINSTACK_TRACE_FILE, none until the close.
 */
#define _GNU_SOURCE
#include <stdio.h>
#include <sys/stat.h>

int main(int argc, char **argv)
{
    if (argc != 2)
        return 2;
    FILE *log = fopen64(argv[1], "w");
    if (!log)
        return 3;
    setvbuf(log, NULL, _IOLBF, 0);
    for (int i = 0; i < 200; i++) {
        fprintf(log, "Trace 0: 0x7f0000000000 [00000000/08000000/00000000/ff200000]\n");
        fflush(log);
    }
    struct stat st;
    if (stat(argv[1], &st) != 0)
        return 4;
    printf("%lld\n", (long long)st.st_size);
    return fclose(log) == 0 ? 0 : 5;
}
