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

function(raymatch_test name)
  cmake_parse_arguments(A "" "LABEL" "SOURCES;DEPS" ${ARGN})
  add_executable(${name} ${A_SOURCES})
  target_link_libraries(${name} PRIVATE ${A_DEPS} raymatch_testing GTest::gtest GTest::gtest_main)
  target_compile_definitions(${name} PRIVATE RAYMATCH_SOURCE_DIR="${PROJECT_SOURCE_DIR}")
  # One ctest entry per test binary keeps ctest output compact; gtest prints the cases.
  add_test(NAME ${name} COMMAND ${name} WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR})
  if(A_LABEL)
    set_tests_properties(${name} PROPERTIES LABELS ${A_LABEL})
  else()
    set_tests_properties(${name} PROPERTIES LABELS fast)
  endif()
endfunction()
