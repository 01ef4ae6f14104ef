// A toy avatar kind: a ball of one colour. It is what a new kind needs and nothing more: this
// folder and one registration line (RegisterToyAvatarKind in the program's avatar kinds). The
// avatar library's tests open, render and export it through the same registry as every kind.
#pragma once

#include <Eigen/Core>
#include <filesystem>

#include "avatar/avatar.h"

namespace holocap::toy {

// Writes a toy model directory (model.json, method "toy"): a ball at `center_m` of `radius_m`,
// its colour BGR in [0, 1].
void WriteToyModel(const std::filesystem::path& dir, const Eigen::Vector3d& center_m,
                   double radius_m, const Eigen::Vector3d& bgr);

// Lets OpenModel open "toy" model directories.
void RegisterToyAvatarKind(AvatarKindRegistry& registry);

}  // namespace holocap::toy
