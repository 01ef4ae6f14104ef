#include <gtest/gtest.h>

#include <fstream>

#include "core/error.h"
#include "core/image.h"
#include "core/mesh.h"
#include "core/report.h"
#include "tests/support/test_support.h"

namespace holocap {
namespace {

using testing::TempDir;

Mesh Tetrahedron() {
  Mesh mesh;
  mesh.vertices = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
  mesh.faces = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
  mesh.colors = {{255, 0, 0}, {0, 255, 0}, {0, 0, 255}, {9, 9, 9}};
  return mesh;
}

TEST(Mesh, PlyRoundTripAndSurfaceSampling) {
  TempDir dir;
  Mesh mesh = Tetrahedron();
  mesh.ComputeNormals();
  WritePly(dir / "m.ply", mesh);
  Mesh back = ReadPly(dir / "m.ply");
  ASSERT_EQ(back.vertices.size(), 4u);
  ASSERT_EQ(back.faces.size(), 4u);
  EXPECT_EQ(back.faces[3], Eigen::Vector3i(1, 2, 3));
  EXPECT_EQ(back.colors[2], mesh.colors[2]);
  EXPECT_NEAR(back.SurfaceArea(), 1.5 + std::sqrt(3.0) / 2, 1e-6);
  auto points = back.SampleSurface(1000, 1);
  for (const auto& p : points) EXPECT_GE(p.minCoeff(), -1e-6);
  auto file = dir / "m.ply";
  std::filesystem::resize_file(file, std::filesystem::file_size(file) - 7);
  EXPECT_THROW(ReadPly(file), Error);
}

TEST(Report, WritesSummaryMetricsAndSeries) {
  TempDir dir;
  Report report("test");
  report.options()["voxel_mm"] = 4;
  report.metrics()["rms"] = 0.25;
  report.AddPoint("rms", 1.0, 0);
  report.AddPoint("rms", 0.25, 1);
  report.SetSummary({Termination::kDegenerate, "only fronto-parallel views"});
  report.Write(dir / "sub/report.json");
  auto json = nlohmann::json::parse(std::ifstream(dir / "sub/report.json"));
  EXPECT_EQ(json["summary"]["termination"], "DEGENERATE");
  EXPECT_EQ(json["series"].size(), 2u);
  EXPECT_EQ(json["series"][1]["metric"], "rms");
  EXPECT_GE(json["series"][1]["t_s"].get<double>(), json["series"][0]["t_s"].get<double>());
  EXPECT_FALSE(IsUsable(Termination::kDegenerate));
}

// One contract for every stage: a summary starts as a failure that never ran, and the CLI's
// exit status follows from the state alone.
TEST(Report, TerminationContract) {
  Summary never_ran;
  EXPECT_EQ(never_ran.termination, Termination::kFailure);
  EXPECT_EQ(never_ran.message, "not run");
  EXPECT_FALSE(never_ran.IsUsable());
  for (Termination usable :
       {Termination::kSuccess, Termination::kConvergence, Termination::kNoConvergence}) {
    EXPECT_TRUE(IsUsable(usable)) << ToString(usable);
    EXPECT_EQ(ExitStatus(usable), 0) << ToString(usable);
  }
  for (Termination unusable : {Termination::kDegenerate, Termination::kFailure}) {
    EXPECT_FALSE(IsUsable(unusable)) << ToString(unusable);
    EXPECT_EQ(ExitStatus(unusable), 1) << ToString(unusable);
  }
  Summary ended;
  ended.End(Termination::kConvergence, "step below 1e-9");
  EXPECT_TRUE(ended.IsUsable());
  EXPECT_EQ(ended.message, "step below 1e-9");
}

TEST(Image, RejectsTruncatedAndForeignFiles) {
  TempDir dir;
  cv::Mat depth(20, 30, CV_32FC1, cv::Scalar(1.5f));
  WriteExrDepth(dir / "d.exr", depth);
  EXPECT_EQ(ReadImage(dir / "d.exr").at<float>(5, 5), 1.5f);
  std::filesystem::resize_file(dir / "d.exr", 100);
  EXPECT_THROW(ReadImage(dir / "d.exr"), Error);
  std::ofstream(dir / "x.png") << "not a png";
  EXPECT_THROW(ReadImage(dir / "x.png"), Error);
  EXPECT_THROW(ReadImage(dir / "x.bmp"), Error);
  cv::Mat mono16(10, 10, CV_16UC1, cv::Scalar(40000));
  WritePng(dir / "m.png", mono16);
  EXPECT_EQ(ReadImage(dir / "m.png").at<uint16_t>(3, 3), 40000);
}

}  // namespace
}  // namespace holocap
