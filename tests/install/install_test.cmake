# ctest install_consumer: install the build tree into WORK_DIR/prefix, configure and build the
# consumer project against it, run it, and import the installed Python module.
file(REMOVE_RECURSE ${WORK_DIR})
set(prefix ${WORK_DIR}/prefix)
function(run)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "failed (${rc}): ${ARGN}\n${out}\n${err}")
  endif()
  set(out "${out}" PARENT_SCOPE)
endfunction()
run(${CMAKE_COMMAND} --install ${BUILD_DIR} --prefix ${prefix})
foreach(f bin/raymatch include/raymatch/core/version.h include/raymatch/simulate/tracer.h)
  if(NOT EXISTS ${prefix}/${f})
    message(FATAL_ERROR "not installed: ${prefix}/${f}")
  endif()
endforeach()
# The build's compiler flags (the sanitize preset's -fsanitize=...: its static libraries need the
# sanitizer runtimes at link time).
run(${CMAKE_COMMAND} -S ${SOURCE_DIR}/consumer -B ${WORK_DIR}/build -G ${GENERATOR}
    -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH=${prefix} "-DCMAKE_CXX_FLAGS=${CXX_FLAGS}")
run(${CMAKE_COMMAND} --build ${WORK_DIR}/build)
run(${WORK_DIR}/build/consumer)
message(STATUS "consumer: ${out}")
if(NOT out MATCHES "^raymatch [0-9.]+ hits [1-9]")
  message(FATAL_ERROR "unexpected consumer output: ${out}")
endif()
run(${prefix}/bin/raymatch --version)
message(STATUS "installed CLI: ${out}")
if(HAVE_PYTHON)
  # Newlines, not semicolons: a semicolon would split the CMake argument.
  run(${CMAKE_COMMAND} -E env PYTHONPATH=${prefix}/${PYTHON_DIR} ${PYTHON_ENV} ${PYTHON} -c "import raymatch, sys
print(raymatch.__version__, raymatch.__file__)
s = raymatch.simulate(raymatch.Scene.from_dict({'camera': {'pixels': [8, 8], 'pixel_pitch_um': 20},
    'source': {'type': 'cone', 'half_angle_deg': 20}, 'objective': {'focal_length_mm': 10, 'na': 0.42,
    'working_distance_mm': 20}, 'tube_lens': {'focal_length_mm': 200}, 'trace': {'rays': 5000}}))
print('hits', s.images[0].sum())
sys.exit(0 if raymatch.__file__.startswith('${prefix}') and s.images[0].sum() > 0 else 1)")
  message(STATUS "installed Python module: ${out}")
endif()
file(REMOVE_RECURSE ${WORK_DIR})
