// The C++ wrapper as installed (<flame.hpp> next to <flame.h>): version, and an error thrown
// as flame::Error with the library's status.
#include <cstdio>

#include <flame.hpp>

int main() {
    std::printf("libflame %s via flame.hpp\n", flame::version().c_str());
    try {
        flame::Model::load("/nonexistent.safetensors");
    } catch (const flame::Error &e) {
        return e.status() == FLAME_STATUS_IO ? 0 : 1;
    }
    return 1;
}
