/* The smallest libflame consumer: prints the library's version, checks that the header and the
 * library agree on the ABI and exits non-zero if they do not. Built by CMake
 * (find_package(flame)) and by pkg-config in tests/c/run.sh. */
#include <stdio.h>
#include <string.h>

#include <flame.h>

int main(void) {
    char expected[32];
    snprintf(expected, sizeof expected, "%d.%d.%d", FLAME_VERSION_MAJOR, FLAME_VERSION_MINOR,
             FLAME_VERSION_PATCH);
    printf("libflame %s (ABI %u)\n", flame_version_string(), flame_abi_version());
    return flame_abi_version() == FLAME_ABI_VERSION && strcmp(flame_version_string(), expected) == 0
               ? 0
               : 1;
}
