#pragma once
// How a file was made: tool version, UTC date, command line, host, input checksums.
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace raymatch {

/// Records the process's command line once (call from main()).
void SetCommandLine(int argc, char** argv);
const std::string& CommandLine();

/// {"tool": "raymatch", "version", "date_utc", "command_line", "host"}.
nlohmann::json ProvenanceJson();

/// ISO-8601 UTC time stamp, YYYY-MM-DDThh:mm:ssZ.
std::string UtcTimestamp();

/// FNV-1a 64-bit checksum of a file's bytes as 16 hex digits (to recognise inputs, not security).
std::string FileChecksum(const std::string& path);

}  // namespace raymatch
