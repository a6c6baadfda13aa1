#pragma once
// Each subcommand lives in its own file and registers itself on the top-level CLI11 app.
// A registration adds a subcommand whose callback sets `*exit_code`.
#include <CLI/CLI.hpp>

namespace raymatch::apps {

void RegisterSimulate(CLI::App& app, int* exit_code);
void RegisterCompare(CLI::App& app, int* exit_code);      // apps/compare.cpp
void RegisterCompareScan(CLI::App& app, int* exit_code);  // apps/compare_scan.cpp
void RegisterProfile(CLI::App& app, int* exit_code);      // apps/profile.cpp
void RegisterCalibrate(CLI::App& app, int* exit_code);
void RegisterRun(CLI::App& app, int* exit_code);          // apps/run.cpp
void RegisterBench(CLI::App& app, int* exit_code);        // apps/bench.cpp ("accuracy")
void RegisterFit(CLI::App& app, int* exit_code);          // apps/fit.cpp
void RegisterSensitivity(CLI::App& app, int* exit_code);  // apps/sensitivity.cpp
void RegisterCapture(CLI::App& app, int* exit_code);      // apps/capture.cpp

/// Runs `fn`, printing raymatch::Error and other exceptions to stderr; returns `error_code` then.
int RunGuarded(const std::function<int()>& fn, int error_code = 1);

}  // namespace raymatch::apps
