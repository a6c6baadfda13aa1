#pragma once
// Write-then-rename so that a failed or interrupted run never leaves a half-written output.
#include <filesystem>
#include <string>

namespace raymatch {

/// A temporary path beside `final_path` that keeps its extension ("a.tif" -> "a.partial-XXXX.tif").
std::filesystem::path TemporaryPathFor(const std::filesystem::path& final_path);

/// Renames `tmp` onto `final_path` (atomic on one filesystem); throws Error on failure.
void CommitTemporary(const std::filesystem::path& tmp, const std::filesystem::path& final_path);

/// Writes text atomically.
void WriteTextFileAtomic(const std::filesystem::path& path, const std::string& text);

/// Creates a directory (and parents); throws Error naming it on failure.
void EnsureDirectory(const std::filesystem::path& dir);

}  // namespace raymatch
