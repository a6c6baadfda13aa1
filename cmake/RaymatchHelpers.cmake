# Small helpers so each library/test is declared the same way (COLMAP CMakeHelper style).
function(raymatch_library name)
  cmake_parse_arguments(A "" "" "SOURCES;PUBLIC_DEPS;PRIVATE_DEPS" ${ARGN})
  add_library(raymatch_${name} STATIC ${A_SOURCES})
  add_library(raymatch::${name} ALIAS raymatch_${name})
  target_include_directories(raymatch_${name} PUBLIC ${CMAKE_CURRENT_SOURCE_DIR}/include
                             PRIVATE ${CMAKE_CURRENT_SOURCE_DIR}/src)
  target_link_libraries(raymatch_${name} PUBLIC ${A_PUBLIC_DEPS} PRIVATE ${A_PRIVATE_DEPS})
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
