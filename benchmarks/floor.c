/* The machine's floor for benchmarks/bench_loop.py: the servo loop's pacing and nothing else,
 * compiled. SCHED_FIFO 80, memory locked, optionally pinned to a CPU; per period: sleep to
 * (deadline - spin) on CLOCK_MONOTONIC (absolute), busy-wait to the deadline, read the clock;
 * whole periods missed are counted and skipped (the deadline re-anchored), as the loop does.
 * With WORK_NS, each period then holds the CPU for WORK_NS by the clock (the loop's turnaround,
 * without its work): how long that takes is what the machine adds to any turnaround (a
 * preemption, a stolen vCPU inside the interval).
 * With LATENCY_US >= 0, the PM QoS CPU latency request the loop holds (loop.realtime.cpu_latency_us:
 * that value written to /dev/cpu_dma_latency, kept open for the run).
 * Usage: floor PERIOD_NS CYCLES SPIN_NS [CPU|-1 [WORK_NS [HOLD_FILE|- [LATENCY_US|-1]]]]; prints
 * "lateness_p50_us p99 p999 max overruns fifo=F mlock=M qos=Q events=E" (E: the wakes that were one
 * or more whole periods late, each counted once however many periods it missed) and, with WORK_NS,
 * "hold=p50/p99/p999/max" [us]; with HOLD_FILE, every period's hold [ns] as native int64 into
 * that file (to pool several runs).
 * Build: cc -O2 -o floor floor.c */
#define _GNU_SOURCE
#include <sched.h>
#include <stdio.h>
#include <fcntl.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>

static long long now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static int cmp(const void *a, const void *b) {
    long long x = *(const long long *)a, y = *(const long long *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    if (argc < 4) return 2;
    long long period = atoll(argv[1]), n = atoll(argv[2]), spin = atoll(argv[3]);
    long long work = argc > 5 ? atoll(argv[5]) : 0;
    if (argc > 4 && atoi(argv[4]) >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET(atoi(argv[4]), &set);
        sched_setaffinity(0, sizeof set, &set);
    }
    struct sched_param sp = {.sched_priority = 80};
    int fifo = sched_setscheduler(0, SCHED_FIFO, &sp) == 0;
    int locked = mlockall(MCL_CURRENT | MCL_FUTURE) == 0;
    int qos = 0;
    if (argc > 7 && atoi(argv[7]) >= 0) {
        int fd = open("/dev/cpu_dma_latency", O_WRONLY), lat = atoi(argv[7]);
        qos = fd >= 0 && write(fd, &lat, sizeof lat) == (ssize_t)sizeof lat;   /* held until exit */
    }
    long long *late = malloc(sizeof(long long) * n), *hold = malloc(sizeof(long long) * n), missed = 0, events = 0;
    long long deadline = now_ns() + period;
    for (long long k = 0; k < n; k++) {
        long long target = deadline - spin;
        struct timespec ts = {target / 1000000000LL, target % 1000000000LL};
        if (target > now_ns()) clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
        while (now_ns() < deadline) {
        }
        late[k] = now_ns() - deadline;
        long long t0 = now_ns(), t1 = t0;
        while (t1 - t0 < work)
            t1 = now_ns();
        hold[k] = t1 - t0;
        if (late[k] >= period) {
            missed += late[k] / period;
            events++;
            deadline += (late[k] / period) * period;
        }
        deadline += period;
    }
    qsort(late, n, sizeof(long long), cmp);
    printf("%.2f %.2f %.2f %.2f %lld fifo=%d mlock=%d qos=%d", late[n / 2] / 1e3, late[(long long)(n * 0.99)] / 1e3,
           late[(long long)(n * 0.999)] / 1e3, late[n - 1] / 1e3, missed, fifo, locked, qos);
    printf(" events=%lld", events);
    if (argc > 6 && strcmp(argv[6], "-") != 0) {
        FILE *f = fopen(argv[6], "wb");
        if (f == NULL || fwrite(hold, sizeof(long long), n, f) != (size_t)n || fclose(f) != 0) return 3;
    }
    if (work > 0) {
        qsort(hold, n, sizeof(long long), cmp);
        printf(" hold=%.2f/%.2f/%.2f/%.2f", hold[n / 2] / 1e3, hold[(long long)(n * 0.99)] / 1e3,
               hold[(long long)(n * 0.999)] / 1e3, hold[n - 1] / 1e3);
    }
    printf("\n");
    return 0;
}
