#pragma once
// Write-then-rename so that a failed or interrupted run never leaves a half-written output.
//
// Every temporary made by TemporaryPathFor is registered until CommitTemporary or
// DiscardTemporary; the first registration installs handlers for SIGINT, SIGTERM and SIGHUP
// (only where the signal still has its default action) that unlink every registered temporary,
// say so on stderr, and end the process by the same signal (so the exit status shows it, e.g.
// 130 for SIGINT in a shell). Up to 256 temporaries (paths under 4096 bytes) are tracked at once;
// the handler uses only async-signal-safe calls (unlink, write, raise) on a fixed array.
#include <filesystem>
#include <string>

namespace raymatch {

/// A temporary path beside `final_path` that keeps its extension ("a.tif" -> "a.partial-XXXX.tif"),
/// registered for removal if the process is interrupted.
std::filesystem::path TemporaryPathFor(const std::filesystem::path& final_path);

/// Renames `tmp` onto `final_path` (atomic on one filesystem) and unregisters it; throws Error
/// on failure (the temporary is then removed).
void CommitTemporary(const std::filesystem::path& tmp, const std::filesystem::path& final_path);

/// Removes an unfinished temporary (no error if it does not exist) and unregisters it.
void DiscardTemporary(const std::filesystem::path& tmp) noexcept;

/// Number of temporaries registered now (tests: 0 after every write has finished or failed).
int RegisteredTemporaries() noexcept;

/// Why a write into `path`'s folder may have failed, for messages: "the disk is full (N bytes
/// free)", "read-only file system", "no permission to write in FOLDER", or "" when none applies.
std::string WriteFailureHint(const std::filesystem::path& path);

/// Writes text atomically; throws Error naming `path` when it cannot (disk full, no permission).
void WriteTextFileAtomic(const std::filesystem::path& path, const std::string& text);

/// Creates a directory (and parents); throws Error naming it on failure. The folders it creates
/// are remembered for RemoveCreatedEmptyDirectories.
void EnsureDirectory(const std::filesystem::path& dir);

/// Removes every folder EnsureDirectory created in this process that is still empty (innermost
/// first; a folder holding anything stays) and forgets them all; returns how many it removed.
/// Commands call it when they fail, so that a refused input leaves no empty output folder.
int RemoveCreatedEmptyDirectories() noexcept;

/// Removes an output that describes a whole run (an index, a stamp) before the run rewrites
/// what it describes, so that an interrupted run does not leave it describing a mix of old and
/// new files; throws Error naming it when it exists and cannot be removed.
void RemoveStaleOutput(const std::filesystem::path& path);

}  // namespace raymatch
