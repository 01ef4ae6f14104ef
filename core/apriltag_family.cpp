#include "core/apriltag_family.h"

#include <cstdint>
#include <cstdlib>
#include <cstring>

#include "core/error.h"

extern "C" {
#include <apriltag/apriltag.h>
#include <apriltag/tag36h11.h>
#include <apriltag/tagStandard41h12.h>
}

namespace holocap {
namespace {

// The name libapriltag gives a family tells which of its destructors frees it; the widened
// families are holocap's own allocation, marked by this name suffix.
constexpr const char* kWidenedSuffix = " (2-bit border)";

bool IsWidened(const apriltag_family* family) {
  return family->name != nullptr && std::strstr(family->name, kWidenedSuffix) != nullptr;
}

template <typename T>
T* CopyArray(const T* source, size_t count) {
  T* copy = static_cast<T*>(std::calloc(count, sizeof(T)));
  if (copy == nullptr) Fail("out of memory for an AprilTag family");
  std::memcpy(copy, source, count * sizeof(T));
  return copy;
}

}  // namespace

void ApriltagFamilyDeleter::operator()(apriltag_family* family) const {
  if (family == nullptr) return;
  if (IsWidened(family)) {
    std::free(family->codes);
    std::free(family->bit_x);
    std::free(family->bit_y);
    std::free(family->name);
    std::free(family);
  } else if (std::strcmp(family->name, "tag36h11") == 0) {
    tag36h11_destroy(family);
  } else {
    tagStandard41h12_destroy(family);
  }
}

ApriltagFamilyPtr CreateApriltagFamily(const std::string& name, int border_bits) {
  if (border_bits != 1 && border_bits != 2)
    Fail("an AprilTag border is 1 or 2 bits wide, got ", border_bits);
  if (name == "tagStandard41h12") {
    if (border_bits != 1) Fail("tagStandard41h12 has no ", border_bits, "-bit border");
    return ApriltagFamilyPtr(tagStandard41h12_create());
  }
  if (name != "tag36h11")
    Fail("unknown AprilTag family '", name, "' (known: tag36h11, tagStandard41h12)");
  ApriltagFamilyPtr base(tag36h11_create());
  if (border_bits == 1) return base;
  auto* family = static_cast<apriltag_family*>(std::calloc(1, sizeof(apriltag_family)));
  if (family == nullptr) Fail("out of memory for an AprilTag family");
  *family = *base;
  family->impl = nullptr;
  family->codes = nullptr;
  family->bit_x = nullptr;
  family->bit_y = nullptr;
  const std::string widened = name + kWidenedSuffix;
  family->name = static_cast<char*>(std::calloc(widened.size() + 1, 1));
  if (family->name == nullptr) {
    std::free(family);
    Fail("out of memory for an AprilTag family");
  }
  std::memcpy(family->name, widened.c_str(), widened.size());
  ApriltagFamilyPtr result(family);  // frees what is copied below, should a copy fail
  family->codes = CopyArray(base->codes, base->ncodes);
  family->bit_x = CopyArray(base->bit_x, base->nbits);
  family->bit_y = CopyArray(base->bit_y, base->nbits);
  const int extra = border_bits - 1;
  for (uint32_t k = 0; k < family->nbits; ++k) {
    family->bit_x[k] += extra;
    family->bit_y[k] += extra;
  }
  family->width_at_border += 2 * extra;
  family->total_width += 2 * extra;
  return result;
}

}  // namespace holocap
