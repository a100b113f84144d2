/* Run a process as if its CPU had AVX2 + FMA + F16C and nothing wider: a preloaded library that
 * hides AVX-512 (every subset), AVX512_BF16/FP16, VNNI (AVX-512 and VEX) and AMX from the
 * `cpuid` instruction, so every library in the process (libflame's dispatch, ONNX Runtime's
 * MLAS, PyTorch's oneDNN and MKL) picks its AVX2 code, on the same hardware.
 *
 * How: Linux's CPUID faulting (`arch_prctl(ARCH_SET_CPUID, 0)`, needs the `cpuid_fault` CPU
 * flag) makes `cpuid` raise SIGSEGV; the handler runs the real instruction with faulting off
 * for that one instruction, clears the bits and steps over it. The setting is per thread and
 * inherited by threads and forks made later, so it is set once, before the program's own code.
 *
 * Only the process's view changes: the CPU still runs at Zen 4 (or whatever) speed per AVX2
 * instruction, so this stands in for an AVX2-only CPU's instruction set, not for its timing.
 *
 *   gcc -O2 -shared -fPIC -o avx2_only.so avx2_only.c -ldl
 *   LD_PRELOAD=$PWD/avx2_only.so COMMAND...      (tools/avx2_only.sh does both)
 *
 * Programs that install their own SIGSEGV handler (rustc does, for stack overflows) keep it:
 * `sigaction` is wrapped so that their handler is recorded and called for every fault that is
 * not a `cpuid`, while this one stays installed.
 *
 * AVX2_ONLY_VERBOSE=1 reports on stderr whether it took effect. AVX2_ONLY_KEEP_AVX_VNNI=1 leaves
 * AVX-VNNI (the VEX `vpdpbusd` on 256 bits) visible on a CPU that has it: the instruction set of
 * an AVX2 CPU with AVX-VNNI and no AVX-512 (Intel's client cores since Alder Lake). */
#define _GNU_SOURCE
#include <asm/prctl.h>
#include <dlfcn.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <ucontext.h>
#include <unistd.h>

static long set_cpuid(int on) { return syscall(SYS_arch_prctl, ARCH_SET_CPUID, on); }

static void real_cpuid(uint32_t leaf, uint32_t sub, uint32_t r[4]) {
    __asm__ volatile("cpuid" : "=a"(r[0]), "=b"(r[1]), "=c"(r[2]), "=d"(r[3]) : "a"(leaf), "c"(sub));
}

/* Leaf 7 bits that an AVX2-only CPU does not set (Intel SDM vol. 2A, CPUID). */
#define BIT(n) (1u << (n))
static const uint32_t L7_EBX = BIT(16) | BIT(17) | BIT(21) | BIT(26) | BIT(27) | BIT(28) |
                               BIT(30) | BIT(31); /* AVX512 F DQ IFMA PF ER CD BW VL */
static const uint32_t L7_ECX = BIT(1) | BIT(6) | BIT(11) | BIT(12) |
                               BIT(14); /* AVX512 VBMI VBMI2 VNNI BITALG VPOPCNTDQ */
static const uint32_t L7_EDX = BIT(2) | BIT(3) | BIT(8) | BIT(22) | BIT(23) | BIT(24) |
                               BIT(25); /* 4VNNIW 4FMAPS VP2INTERSECT AMX-BF16 FP16 AMX-TILE AMX-INT8 */
static const uint32_t L7_1_EAX = BIT(4) | BIT(5) | BIT(21) | BIT(22) |
                                 BIT(23); /* AVX-VNNI AVX512_BF16 AMX-FP16 HRESET AVX-IFMA */

/* Set once by the constructor: AVX2_ONLY_KEEP_AVX_VNNI=1. */
static int keep_avx_vnni;

static void mask(uint32_t leaf, uint32_t sub, uint32_t r[4]) {
    if (leaf == 7 && sub == 0) {
        r[1] &= ~L7_EBX;
        r[2] &= ~L7_ECX;
        r[3] &= ~L7_EDX;
    } else if (leaf == 7 && sub == 1) {
        r[0] &= ~(keep_avx_vnni ? L7_1_EAX & ~BIT(4) : L7_1_EAX);
    } else if (leaf == 0xd && sub == 0) {
        r[0] &= ~(BIT(5) | BIT(6) | BIT(7) | BIT(17) | BIT(18)); /* opmask, ZMM, AMX states */
    }
}

typedef int (*sigaction_fn)(int, const struct sigaction *, struct sigaction *);
static sigaction_fn real_sigaction;
/* The program's own SIGSEGV disposition (SIG_DFL until it sets one). */
static struct sigaction program_segv;

static void on_segv(int sig, siginfo_t *info, void *ctx) {
    ucontext_t *uc = ctx;
    greg_t *g = uc->uc_mcontext.gregs;
    const unsigned char *ip = (const unsigned char *)g[REG_RIP];
    if (info->si_code != SI_KERNEL || ip[0] != 0x0f || ip[1] != 0xa2) {
        /* A real fault: the program's handler, or the default action (the fault repeats on
         * return and kills the process as it would have). */
        if (program_segv.sa_flags & SA_SIGINFO) {
            program_segv.sa_sigaction(sig, info, ctx);
        } else if (program_segv.sa_handler != SIG_DFL && program_segv.sa_handler != SIG_IGN) {
            program_segv.sa_handler(sig);
        } else {
            struct sigaction dfl;
            memset(&dfl, 0, sizeof dfl);
            dfl.sa_handler = SIG_DFL;
            real_sigaction(sig, &dfl, NULL);
        }
        return;
    }
    uint32_t leaf = (uint32_t)g[REG_RAX], sub = (uint32_t)g[REG_RCX], r[4];
    set_cpuid(1);
    real_cpuid(leaf, sub, r);
    set_cpuid(0);
    mask(leaf, sub, r);
    g[REG_RAX] = r[0];
    g[REG_RBX] = r[1];
    g[REG_RCX] = r[2];
    g[REG_RDX] = r[3];
    g[REG_RIP] += 2;
}

/* The program sees its own SIGSEGV disposition; every other signal goes through. */
int sigaction(int sig, const struct sigaction *act, struct sigaction *old) {
    if (!real_sigaction) real_sigaction = (sigaction_fn)dlsym(RTLD_NEXT, "sigaction");
    if (sig != SIGSEGV) return real_sigaction(sig, act, old);
    if (old) *old = program_segv;
    if (act) program_segv = *act;
    return 0;
}

__attribute__((constructor)) static void avx2_only(void) {
    int verbose = getenv("AVX2_ONLY_VERBOSE") && strcmp(getenv("AVX2_ONLY_VERBOSE"), "1") == 0;
    keep_avx_vnni = getenv("AVX2_ONLY_KEEP_AVX_VNNI") &&
                    strcmp(getenv("AVX2_ONLY_KEEP_AVX_VNNI"), "1") == 0;
    real_sigaction = (sigaction_fn)dlsym(RTLD_NEXT, "sigaction");
    program_segv.sa_handler = SIG_DFL;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = on_segv;
    sa.sa_flags = SA_SIGINFO | SA_NODEFER | SA_ONSTACK;
    sigemptyset(&sa.sa_mask);
    if (!real_sigaction || real_sigaction(SIGSEGV, &sa, NULL) != 0 || set_cpuid(0) != 0) {
        fprintf(stderr, "avx2_only: CPUID faulting unavailable (no cpuid_fault flag?); nothing hidden\n");
        return;
    }
    if (verbose)
        fprintf(stderr, "avx2_only: AVX-512, %s, BF16 and AMX hidden from cpuid\n",
                keep_avx_vnni ? "AVX512_VNNI (AVX-VNNI kept)" : "VNNI");
}
