# `cmake --install`: the CLI, the static libraries with their headers (and the generated
# version.h), a CMake package (find_package(raymatch) -> raymatch::core, raymatch::simulate, ...)
# and, when built, the Python module (python/CMakeLists.txt). docs/install.md.
include(CMakePackageConfigHelpers)

install(TARGETS raymatch RUNTIME DESTINATION ${CMAKE_INSTALL_BINDIR} COMPONENT cli)
install(FILES ${CMAKE_BINARY_DIR}/generated/raymatch/core/version.h
        DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/raymatch/core COMPONENT development)

set(RAYMATCH_CMAKE_DIR ${CMAKE_INSTALL_LIBDIR}/cmake/raymatch)
install(EXPORT raymatchTargets NAMESPACE raymatch:: DESTINATION ${RAYMATCH_CMAKE_DIR}
        COMPONENT development)
set(RAYMATCH_COMPONENTS)
foreach(_lib core simulate compare calibrate fit pipeline)
  if(TARGET raymatch_${_lib})
    list(APPEND RAYMATCH_COMPONENTS ${_lib})
  endif()
endforeach()
configure_package_config_file(${CMAKE_CURRENT_LIST_DIR}/raymatchConfig.cmake.in
  ${CMAKE_BINARY_DIR}/raymatchConfig.cmake INSTALL_DESTINATION ${RAYMATCH_CMAKE_DIR})
write_basic_package_version_file(${CMAKE_BINARY_DIR}/raymatchConfigVersion.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES ${CMAKE_BINARY_DIR}/raymatchConfig.cmake ${CMAKE_BINARY_DIR}/raymatchConfigVersion.cmake
        DESTINATION ${RAYMATCH_CMAKE_DIR} COMPONENT development)
