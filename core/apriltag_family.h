// libapriltag's tag families as holocap's boards use them, including tag36h11 as Kalibr prints
// it: Kalibr's kalibr_create_target_pdf draws each tag with a black border two bits wide (its
// detector runs with blackTagBorder = 2), where libapriltag's tag36h11 expects one.
#pragma once

#include <memory>
#include <string>

extern "C" {
struct apriltag_family;
}

namespace holocap {

struct ApriltagFamilyDeleter {
  void operator()(apriltag_family* family) const;
};
using ApriltagFamilyPtr = std::unique_ptr<apriltag_family, ApriltagFamilyDeleter>;

// A new instance of libapriltag's family `name` ("tag36h11" or "tagStandard41h12") with a black
// border `border_bits` wide: 1 as libapriltag draws it, or 2 (tag36h11 only) as Kalibr prints
// it. The two-bit family has libapriltag's codes and bit order, every data bit one bit further
// in and the detection square (width_at_border, the black square's side) and total_width two
// bits wider, so libapriltag's decoder samples the data bits, its black model the outermost
// border bit and its white model the bit just outside the black square, as for the one-bit
// family. Each detector needs its own instance: libapriltag keeps its decode table in it.
// Throws Error for an unknown name or a border the family cannot have.
ApriltagFamilyPtr CreateApriltagFamily(const std::string& name, int border_bits = 1);

}  // namespace holocap
