# Work-around for the ROS 2 Jazzy wheels on PyPI; not needed with a stock ROS install.
#
# The exported *__rosidl_generator_py targets in those wheels name an include folder of the
# machine that built them (/opt/python/cp311-cp311/include/python3.11). CMake's generate step
# refuses imported targets whose INTERFACE_INCLUDE_DIRECTORIES do not exist, so a package that
# generates Python messages depending on std_msgs etc. cannot be configured.
#
# Use without touching the package's CMakeLists.txt:
#   cmake -DCMAKE_PROJECT_INCLUDE=/path/to/drop_missing_includes.cmake ...
#   colcon build --cmake-args -DCMAKE_PROJECT_INCLUDE=/path/to/drop_missing_includes.cmake
# It is included after every project() call and defers one pass, run when the top-level
# CMakeLists.txt has been processed (before generation), that removes every absolute include
# folder that does not exist from the imported targets of all directories. Entries with
# generator expressions are left alone.
cmake_minimum_required(VERSION 3.21)  # cmake_language(DEFER), IMPORTED_TARGETS

function(_formopt_drop_missing_includes_in_dir dir)
  get_directory_property(targets DIRECTORY "${dir}" IMPORTED_TARGETS)
  foreach(target IN LISTS targets)
    get_target_property(includes "${target}" INTERFACE_INCLUDE_DIRECTORIES)
    if(NOT includes)
      continue()
    endif()
    set(kept "")
    set(dropped "")
    foreach(inc IN LISTS includes)
      if(inc MATCHES "\\$<" OR NOT IS_ABSOLUTE "${inc}" OR EXISTS "${inc}")
        list(APPEND kept "${inc}")
      else()
        list(APPEND dropped "${inc}")
      endif()
    endforeach()
    if(dropped)
      set_property(TARGET "${target}" PROPERTY INTERFACE_INCLUDE_DIRECTORIES "${kept}")
      message(STATUS "drop_missing_includes: ${target}: dropped ${dropped}")
    endif()
  endforeach()
  get_directory_property(subdirs DIRECTORY "${dir}" SUBDIRECTORIES)
  foreach(subdir IN LISTS subdirs)
    _formopt_drop_missing_includes_in_dir("${subdir}")
  endforeach()
endfunction()

function(_formopt_drop_missing_includes)
  _formopt_drop_missing_includes_in_dir("${CMAKE_SOURCE_DIR}")
endfunction()

get_property(_formopt_dmi_deferred GLOBAL PROPERTY _FORMOPT_DROP_MISSING_INCLUDES_DEFERRED)
if(NOT _formopt_dmi_deferred)
  set_property(GLOBAL PROPERTY _FORMOPT_DROP_MISSING_INCLUDES_DEFERRED TRUE)
  cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _formopt_drop_missing_includes)
endif()
unset(_formopt_dmi_deferred)
