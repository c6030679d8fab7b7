#include "core/opc/image_codec.hpp"

#include <dlfcn.h>

#include <cstdlib>
#include <string>

#include "core/common/error.hpp"

// Weak: null unless the binary links the module's source in.
extern "C" const vsm::core::image::Codec* vsm_image_codec() __attribute__((weak));

namespace vsm::core::image {

namespace {

const Codec* load() {
  if (vsm_image_codec != nullptr) {
    return vsm_image_codec();
  }
  const char* override = std::getenv("VSM_IMAGE_MODULE");
  const std::string module =
      override != nullptr && *override != '\0' ? override : "libvsm_image.so";
  // RTLD_LOCAL: OpenImageIO's symbols stay out of the global scope; the handle is never closed.
  void* handle = dlopen(module.c_str(), RTLD_NOW | RTLD_LOCAL);
  if (handle == nullptr) {
    throw Error(ErrorCode::Internal,
                "cannot load " + module + ", vsm's OpenImageIO module for texture images (" +
                    dlerror() +
                    "); install it where the dynamic linker finds it (/usr/local/lib, then "
                    "ldconfig) or set VSM_IMAGE_MODULE to its path");
  }
  using Entry = const Codec* (*)();
  auto entry = reinterpret_cast<Entry>(dlsym(handle, "vsm_image_codec"));
  if (entry == nullptr) {
    throw Error(ErrorCode::Internal, module + " is not vsm's image module: no vsm_image_codec");
  }
  return entry();
}

}  // namespace

const Codec& codec() {
  // A throwing initialiser leaves it uninitialised: the next call tries again.
  static const Codec* const loaded = load();
  return *loaded;
}

}  // namespace vsm::core::image
