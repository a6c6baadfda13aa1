# Small helpers so each library/test is declared the same way (COLMAP CMakeHelper style).
function(raymatch_library name)
  cmake_parse_arguments(A "" "" "SOURCES;PUBLIC_DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(raymatch_${name} STATIC ${A_SOURCES})
  add_library(raymatch::${name} ALIAS raymatch_${name})
  target_include_directories(raymatch_${name}
                             PUBLIC $<BUILD_INTERFACE:${CMAKE_CURRENT_SOURCE_DIR}/include>
                                    $<INSTALL_INTERFACE:${CMAKE_INSTALL_INCLUDEDIR}>
                             PRIVATE ${CMAKE_CURRENT_SOURCE_DIR}/src)
  target_link_libraries(raymatch_${name} PUBLIC ${A_PUBLIC_DEPS} PRIVATE ${A_PRIVATE_DEPS})
  # Position-independent so the Python module (a shared object) and installed consumers' shared
  # libraries can link the static libraries (docs/performance.md: no measurable cost to the tracer).
  # EXPORT_NAME: the installed package's imported target is raymatch::${name}, like the alias.
  set_target_properties(raymatch_${name} PROPERTIES POSITION_INDEPENDENT_CODE ON EXPORT_NAME ${name})
  install(TARGETS raymatch_${name} EXPORT raymatchTargets
          ARCHIVE DESTINATION ${CMAKE_INSTALL_LIBDIR} COMPONENT development)
  install(DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR}/include/ DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}
          COMPONENT development PATTERN "*.in" EXCLUDE)
  # -Wno-restrict: GCC 12 false positive in std::string concatenation (GCC bug 105329).
  target_compile_options(raymatch_${name} PRIVATE -Wall -Wextra -Wno-unused-parameter -Wno-restrict)
endfunction()

# A GoogleTest binary whose cases are registered one by one (`ctest -N` lists them as
# binary.Suite.Case), so that a GTEST_SKIP shows as skipped (GoogleTest's module marks it), not
# as a passed binary. Cases are listed when ctest runs (PRE_TEST), not at build time. LABEL: `fast` (default) or
# `slow` (left out of the default set). TIMEOUT: seconds per case (default 600); every case has one.
function(raymatch_test name)
  cmake_parse_arguments(A "" "LABEL;TIMEOUT" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${A_SOURCES})
  target_link_libraries(${name} PRIVATE ${A_DEPS} raymatch_testing GTest::gtest GTest::gtest_main)
  target_compile_definitions(${name} PRIVATE RAYMATCH_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  if(NOT A_LABEL)
    set(A_LABEL fast)
  endif()
  if(NOT A_TIMEOUT)
    set(A_TIMEOUT 600)
  endif()
  # Under the sanitizers everything runs several times slower.
  if(CMAKE_CXX_FLAGS MATCHES "-fsanitize=")
    math(EXPR A_TIMEOUT "${A_TIMEOUT} * 5")
  endif()
  gtest_discover_tests(${name} TEST_PREFIX "${name}." WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR}
                       DISCOVERY_MODE PRE_TEST DISCOVERY_TIMEOUT 120
                       PROPERTIES LABELS "${A_LABEL};${name}" TIMEOUT ${A_TIMEOUT})
endfunction()
