/* What fresh memory costs on this machine: the time to touch every page of
 * a new anonymous mapping (the kernel's page faults and the backing of each
 * page), the floor of a loader's first fill, whose bricks are all new
 * memory. Also with the mapping populated in one call (MAP_POPULATE,
 * MADV_POPULATE_WRITE) and with transparent huge pages (MADV_HUGEPAGE).
 *
 *   cc -O2 -o /tmp/fresh-pages scripts/fresh-pages.c && /tmp/fresh-pages [MiB] [rounds]
 */
#define _GNU_SOURCE
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <time.h>

#ifndef MADV_POPULATE_WRITE
#define MADV_POPULATE_WRITE 23
#endif

static double now(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec * 1e-9;
}

static const char *names[] = {"touch each page", "MAP_POPULATE", "MADV_POPULATE_WRITE",
                              "MADV_HUGEPAGE, touch"};

int main(int argc, char **argv) {
    size_t mib = argc > 1 ? strtoul(argv[1], 0, 10) : 376;
    int rounds = argc > 2 ? atoi(argv[2]) : 3;
    size_t n = mib << 20, pages = n / 4096;
    for (int r = 0; r < rounds; r++) {
        for (int mode = 0; mode < 4; mode++) {
            int flags = MAP_PRIVATE | MAP_ANONYMOUS | (mode == 1 ? MAP_POPULATE : 0);
            double t0 = now();
            char *p = mmap(0, n, PROT_READ | PROT_WRITE, flags, -1, 0);
            if (p == MAP_FAILED) {
                perror("mmap");
                return 1;
            }
            if (mode == 2 && madvise(p, n, MADV_POPULATE_WRITE) != 0)
                perror("madvise(MADV_POPULATE_WRITE)");
            if (mode == 3)
                madvise(p, n, MADV_HUGEPAGE);
            if (mode == 0 || mode == 3)
                for (size_t i = 0; i < n; i += 4096)
                    p[i] = 1;
            double t1 = now();
            for (size_t i = 0; i < n; i += 64)
                p[i] = 2;
            double t2 = now();
            printf("round %d, %-22s %zu MiB: %.3f s (%.2f us/page), a write pass after %.3f s\n",
                   r + 1, names[mode], mib, t1 - t0, (t1 - t0) / pages * 1e6, t2 - t1);
            munmap(p, n);
        }
    }
    return 0;
}
