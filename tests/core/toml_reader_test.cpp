#include "raymatch/core/toml_reader.h"

#include <gtest/gtest.h>

#include "temp_dir.h"

namespace raymatch {
namespace {

std::string ErrorOf(const std::string& text, const std::function<void(TomlReader&)>& read) {
  testing::TempDir dir;
  const std::string path = dir.Write("s.toml", text);
  try {
    toml::table t = ParseTomlFile(path);
    TomlReader r(t, "s.toml", "");
    read(r);
    r.Finish();
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST(TomlReader, SyntaxErrorHasLineAndColumn) {
  const std::string e = ErrorOf("a = 1\nb = [1, 2\n", [](TomlReader&) {});
  EXPECT_NE(e.find("s.toml:"), std::string::npos) << e;
  EXPECT_NE(e.find("TOML syntax"), std::string::npos) << e;
}

TEST(TomlReader, UnknownKeyIsAnErrorWithItsPosition) {
  const std::string e =
      ErrorOf("radius = 1\nradus = 2\n", [](TomlReader& r) { r.Positive("radius"); });
  EXPECT_NE(e.find("s.toml:2:1: error: unknown key 'radus'"), std::string::npos) << e;
  EXPECT_NE(e.find("accepted here: radius"), std::string::npos) << e;
}

TEST(TomlReader, WrongTypeNamesExpectedAndActual) {
  const std::string e = ErrorOf("[obj]\nradius = \"big\"\n", [](TomlReader& r) {
    auto t = r.Table("obj");
    t.Positive("radius");
  });
  EXPECT_NE(e.find("s.toml:2:10: error: 'obj.radius': expected a number, got a string"),
            std::string::npos)
      << e;
}

TEST(TomlReader, ImpossibleNumbersAreRejected) {
  EXPECT_NE(ErrorOf("r = -3\n", [](TomlReader& r) { r.Positive("r"); })
                .find("s.toml:1:5: error: 'r': expected a positive number"),
            std::string::npos);
  EXPECT_NE(ErrorOf("na = 1.0\n", [](TomlReader& r) { r.InRange("na", 0, 1, 0.5, true, true); })
                .find("expected a number in (0, 1)"),
            std::string::npos);
  EXPECT_NE(ErrorOf("n = 0\n", [](TomlReader& r) { r.Integer("n", 1, 1, 100); })
                .find("expected an integer in [1, 100], got 0"),
            std::string::npos);
}

TEST(TomlReader, MissingKeyNamesTheTable) {
  const std::string e = ErrorOf("[obj]\nx = 1\n", [](TomlReader& r) {
    auto t = r.Table("obj");
    t.Number("x");
    t.Positive("radius_um");
  });
  EXPECT_NE(e.find("missing required key 'obj.radius_um' in [obj]"), std::string::npos) << e;
}

// A misspelled required key is named where it is written, with the key it resembles; so is a
// misspelled table; a key far from every expected one gets no guess.
TEST(TomlReader, MisspelledKeysAreNamedWithTheNearestValidKey) {
  std::string e = ErrorOf("[obj]\nx = 1\nraduis_um = 30\n", [](TomlReader& r) {
    auto t = r.Table("obj");
    t.Number("x");
    t.Positive("radius_um");
  });
  EXPECT_NE(e.find("s.toml:3:1"), std::string::npos) << e;
  EXPECT_NE(e.find("found 'obj.raduis_um': did you mean 'radius_um'?"), std::string::npos) << e;
  e = ErrorOf("[tubelens]\nf = 1\n", [](TomlReader& r) { r.Table("tube_lens"); });
  EXPECT_NE(e.find("found 'tubelens': did you mean 'tube_lens'?"), std::string::npos) << e;
  e = ErrorOf("[obj]\ncolour = 1\n", [](TomlReader& r) { r.Table("obj").Positive("radius_um"); });
  EXPECT_EQ(e.find("did you mean"), std::string::npos) << e;
  // An optional key misspelled: the unknown-key error suggests it.
  e = ErrorOf("index = 1.33\nradus = 2\n", [](TomlReader& r) {
    r.Number("index");
    r.Positive("radius", 1.0);
  });
  EXPECT_NE(e.find("unknown key 'radus': did you mean 'radius'?"), std::string::npos) << e;
}

TEST(TomlReader, ChoicesAndArrays) {
  EXPECT_NE(ErrorOf("t = \"cube\"\n",
                    [](TomlReader& r) {
                      r.Choice("t", {"sphere", "box"});
                    })
                .find("expected one of \"sphere\", \"box\", got \"cube\""),
            std::string::npos);
  EXPECT_NE(
      ErrorOf("c = [1, 2]\n", [](TomlReader& r) { r.Vec3("c"); }).find("expected 3 numbers, got 2"),
      std::string::npos);
  EXPECT_EQ(ErrorOf("c = [1, 2, 3]\nok = true\n",
                    [](TomlReader& r) {
                      EXPECT_DOUBLE_EQ(r.Vec3("c")[2], 3.0);
                      EXPECT_TRUE(r.Bool("ok", false));
                    }),
            "");
}

}  // namespace
}  // namespace raymatch
