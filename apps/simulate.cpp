#include "commands.h"
namespace raymatch::apps {
void RegisterSimulate(CLI::App& app, int* exit_code) {}
}
