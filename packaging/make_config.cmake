# cmake -DDAEMON=cortexfused -DOUT=file -DSHARE=/usr/share/cortexfuse -P make_config.cmake
# Writes the daemon's default configuration with the data and UI paths of the installed layout.
execute_process(COMMAND ${DAEMON} --print-default-config OUTPUT_VARIABLE cfg RESULT_VARIABLE rc)
if(NOT rc EQUAL 0)
  message(FATAL_ERROR "${DAEMON} --print-default-config exited ${rc}")
endif()
string(JSON cfg SET "${cfg}" data t1 "\"${SHARE}/data/t1_head_mne_ecog.nii.gz\"")
string(JSON cfg SET "${cfg}" data brain_mask "\"${SHARE}/data/brainmask_mne_ecog_binary.nii.gz\"")
string(JSON cfg SET "${cfg}" http ui_dir "\"${SHARE}/ui\"")
file(WRITE ${OUT} "${cfg}\n")
